"""Every Warp kernel module builds ahead of time for the GPUs the design card names, without a GPU: sm_86 (RTX 30xx,
the papers' desktop GPUs) and sm_87 (Jetson Orin), with Warp's bundled NVRTC (`wp.compile_aot_module`). A change
that breaks CUDA code generation (a construct Warp cannot lower to CUDA, an NVRTC error) fails here, although the
CPU tests, which compile the same kernels with LLVM, still pass. perf/gpu_codegen.py holds the builder and the
cubin reader; docs/gpu.md the resulting register / occupancy table."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

gpu_codegen = pytest.importorskip("swarmsplat.perf.gpu_codegen")


@pytest.fixture(scope="module")
def modules():
    return gpu_codegen.warp_modules()


def test_every_kernel_file_contributes_a_module(modules):
    """Read from the sources, independently of the discovery: every kernels/_warp file that defines a Warp kernel
    contributes its module, and one that makes kernels inside a function (a factory) lists them in aot_kernels();
    a file marked `CPU_ONLY = True` (vector code for the CPU, never launched on CUDA) is left out."""
    import importlib
    import pkgutil
    import re

    import swarmsplat.kernels._warp as pkg

    with_kernels = 0
    for info in pkgutil.iter_modules(pkg.__path__):
        src = (Path(pkg.__path__[0]) / f"{info.name}.py").read_text()
        if re.search(r"^CPU_ONLY = True", src, re.M):
            assert f"{pkg.__name__}.{info.name}" not in modules, info.name
            continue
        if re.search(r"^@wp\.kernel", src, re.M):
            assert f"{pkg.__name__}.{info.name}" in modules, info.name
            with_kernels += 1
        if re.search(r"^[ \t]+@wp\.kernel", src, re.M):
            assert hasattr(importlib.import_module(f"{pkg.__name__}.{info.name}"), "aot_kernels"), info.name
    assert with_kernels >= 4  # axpy, icp, project, raster at least
    assert sum(1 for name in modules if name in gpu_codegen.LABELS) == 4  # the ICP reduction specialisations


@pytest.mark.parametrize("arch", gpu_codegen.ARCHS)
def test_every_warp_module_builds_for_the_gpu(modules, arch):
    import warp as wp

    # Warp's versioned kernel cache: a cubin is named by the module's content hash, so an unchanged module is
    # not rebuilt on the next run and a changed one always is.
    cache = Path(wp.config.kernel_cache_dir) / "aot"
    for name, module in modules.items():
        cubin = gpu_codegen.build(module, arch, cache)
        data = cubin.read_bytes()
        assert data[:4] == b"\x7fELF" and struct.unpack_from("<H", data, 18)[0] == 190, name  # EM_CUDA
        res = gpu_codegen.cubin_resources(data)
        # One CUDA entry point per Warp kernel of the module (forward only: no adjoints are compiled).
        n_kernels = len([k for k in module.kernels.values() if isinstance(k, wp.Kernel)])
        assert len(res) == n_kernels, (name, sorted(res))
        for sym, r in res.items():
            assert 0 < r["registers"] <= 255 and r["frame_bytes"] < 4096, (name, sym, r)


def test_cubin_reader_and_occupancy_arithmetic():
    # 20 registers: 8 blocks of 256 threads fit by registers, 6 by the 48-warp limit -> full occupancy.
    assert gpu_codegen.occupancy(20) == 1.0
    # 160 registers: 5120 per warp, 12 warps by registers, one 8-warp block of 256 threads -> 8/48.
    assert gpu_codegen.occupancy(160) == pytest.approx(8 / 48)
    assert gpu_codegen.occupancy(160, block=128) == pytest.approx(12 / 48)
    with pytest.raises(ValueError, match="ELF64"):
        gpu_codegen.cubin_resources(b"not a cubin")


def test_jetson_xavier_sm72_needs_a_cuda12_warp(modules, tmp_path):
    """Warp builds whose NVRTC is CUDA 13 refuse sm_72 (CUDA 13 dropped offline compilation for Volta, so Jetson
    AGX Xavier); a CUDA 12 build of Warp (+cu12 wheel or source) accepts it. docs/gpu.md says which to install."""
    import warp._src.context as ctx

    toolkit = ctx.runtime.toolkit_version
    module = modules["swarmsplat.kernels._warp.axpy"]
    if toolkit[0] >= 13:
        with pytest.raises(Exception, match="build failed"):
            gpu_codegen.build(module, 72, tmp_path)
    else:
        assert gpu_codegen.build(module, 72, tmp_path).exists()
