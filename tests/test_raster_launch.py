"""The Warp rasteriser's CPU launch plumbing (kernels/_warp/launch.py) changes no bit of the results: direct calls
of the compiled kernels against wp.launch, and launches split over threads against single launches, forward and
backward, on the perf scene (big enough that projection and compositing split over the cores)."""

from __future__ import annotations

import pytest
import torch

from swarmsplat import kernels
from swarmsplat.perf.raster import _loss, _params, make_scene


def _run(scene):
    p = _params(scene, True)
    p["viewmat"] = scene["viewmat"].clone().requires_grad_(True)
    o = kernels.rasterize(**p)
    _loss(o.color, o.depth, o.alpha).backward()
    outs = [o.color, o.depth, o.depth_normalised, o.alpha, o.radii, o.n_touched]
    return outs + [p[k].grad for k in ("means", "quats", "scales", "opacities", "colors", "viewmat")]


@pytest.fixture
def warp_cpu():
    kernels.use("warp", "cpu")
    from swarmsplat.kernels._warp import launch

    return launch


@pytest.mark.parametrize("size", [(160, 120, 1_000), (320, 240, 20_000)])
def test_direct_calls_equal_wp_launch(warp_cpu, monkeypatch, size):
    w, h, n = size
    scene = make_scene(n, w, h, seed=3)
    _run(scene)  # first launches: compile / load
    direct = _run(scene)
    assert any(v is not None for v in warp_cpu._DIRECT.values())
    monkeypatch.setattr(warp_cpu, "DIRECT", False)
    ref = _run(scene)
    for a, b in zip(direct, ref):
        assert torch.equal(a, b)


def test_packed_arguments_equal_the_ctypes_struct(warp_cpu):
    """run's one-struct.pack argument packing (Flats and scalars) writes the bytes that filling the kernel's ctypes
    argument struct field by field writes; a mistyped argument still gets ctypes' error."""
    from swarmsplat.kernels._warp import loss_cpu
    from swarmsplat.kernels._warp.arrays import to_warp

    h, w = 6, 10
    img = [torch.rand(h * w * 3), torch.rand(h * w * 3), torch.rand(h * w), torch.rand(h * w), torch.rand(h * w)]
    outs = [torch.empty(h * w) for _ in range(3)]
    inputs = [to_warp(t) for t in img] + [w, 4.0, 0] + [to_warp(t) for t in outs]
    warp_cpu.run(loss_cpu.errors, h, inputs, "cpu")  # loads the module
    warp_cpu.run(loss_cpu.errors, h, inputs, "cpu")  # described: direct calls from here on
    hook, struct, _kdim, _bounds, _cmd, packer = warp_cpu._DIRECT[loss_cpu.errors]
    assert packer is not None
    packed = warp_cpu._args(struct, packer, inputs)
    filled = warp_cpu._args(struct, None, inputs)
    assert bytes(packed) == bytes(filled)
    bad = list(inputs)
    bad[5], bad[6] = bad[6], bad[5]  # width (int) and power (float) swapped
    with pytest.raises(TypeError):
        warp_cpu._args(struct, packer, bad)
    bad = list(inputs)
    bad[0], bad[5] = bad[5], bad[0]  # an array and a scalar swapped: not packed into the wrong fields
    with pytest.raises(TypeError):
        warp_cpu._args(struct, packer, bad)


@pytest.mark.parametrize("threads", [2, 3])
def test_split_equal_single_launch(warp_cpu, monkeypatch, threads):
    scene = make_scene(20_000, 320, 240, seed=4)
    monkeypatch.setattr(warp_cpu, "_cpu_threads", lambda: threads)  # binning in `threads` parts, launches split
    _run(scene)
    split = _run(scene)
    monkeypatch.setattr(warp_cpu, "_cpu_threads", lambda: 1)
    one = _run(scene)
    for a, b in zip(split, one):
        assert torch.equal(a, b)


def test_cuda_shapes_on_the_cpu_equal(warp_cpu, monkeypatch):
    """The projection and hit counts one Gaussian per kernel thread (their CUDA shape, count 1: the per-Gaussian
    kernel, viewmat parts per Gaussian summed in blocks of 256 by _view_grad) against the CPU's blocks, both with
    the scalar projection kernels (the CUDA ones; tests/test_project_cpu.py checks the CPU's vector ones)."""
    from swarmsplat.kernels._warp import project, sort

    monkeypatch.setattr(project, "CPU_PROJECT", "scalar")
    scene = make_scene(20_000, 320, 240, seed=5)
    _run(scene)
    blocks = _run(scene)
    monkeypatch.setattr(project, "BLOCK", 1)
    monkeypatch.setattr(sort, "BLOCK", 1)
    _run(scene)
    single = _run(scene)
    for a, b in zip(blocks, single):
        assert torch.equal(a, b)


def test_without_warp_descriptors_results_are_the_same(warp_cpu, monkeypatch):
    """A Warp whose array descriptor layout is not the one kernels/_warp/arrays.py knows gets wp.from_torch arrays
    (and wp.launch's own packing): the same bits, only slower."""
    from swarmsplat.kernels._warp import arrays

    scene = make_scene(1_000, 160, 120, seed=6)
    _run(scene)
    fast = _run(scene)
    monkeypatch.setattr(arrays, "_from", None)
    slow = _run(scene)
    for a, b in zip(fast, slow):
        assert torch.equal(a, b)


@pytest.mark.parametrize("threads", [1, 3])
def test_native_binning_equals_warp_kernels(warp_cpu, monkeypatch, threads):
    """kernels/_warp/sort_cpu.py's binning against kernels/_warp/sort.py's Warp kernels (the CUDA ones): the same
    lists, entry positions and so the same renders and gradients, bit for bit, in one part and in three."""
    from swarmsplat.kernels._warp import sort

    scene = make_scene(20_000, 320, 240, seed=7)
    scene["means"][::5, 2] = scene["means"][0, 2]  # many exact depth ties: the stable order decides
    monkeypatch.setattr(warp_cpu, "_cpu_threads", lambda: threads)
    out = {}
    for mode in ("warp", "native"):
        monkeypatch.setattr(sort, "CPU_SORT", mode)
        _run(scene)
        out[mode] = _run(scene)
    for a, b in zip(out["warp"], out["native"]):
        assert torch.equal(a, b)


def test_view_free_descriptors_equal_those_of_the_views():
    """to_warp_1d / to_warp_rows describe a tensor's flattening and rows as to_warp describes the torch views, and
    refuse a layout they cannot describe without a copy."""
    from swarmsplat.kernels._warp.arrays import to_warp, to_warp_1d, to_warp_rows

    for t in (torch.empty(5, 7), torch.empty(2, 3, 4, dtype=torch.int32), torch.empty(2, 2, 3, 5)):
        assert to_warp_rows(t) == [to_warp(r) for r in t]
    img = torch.rand(6, 4, 3)
    assert to_warp_1d(img) == to_warp(img.view(-1))
    flat = to_warp_1d(torch.zeros(()).expand(6, 4))  # a broadcast scalar: 24 values read at stride 0
    assert flat[2] == 24 and flat[6] == 0
    with pytest.raises(ValueError, match="contiguous or broadcast"):
        to_warp_1d(img.transpose(0, 1))
