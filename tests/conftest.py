"""Shared fixtures: the backend x device matrix (CUDA cases skip without a GPU, Vulkan ones without a Vulkan
driver) and ../shared/data."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", REPO.parent / "shared" / "data"))

BACKEND_CASES = [("warp", "cpu"), ("taichi", "cpu"), ("warp", "cuda"), ("taichi", "cuda")]
# Taichi on Vulkan (SPIR-V): run only by the modules that check the kernels themselves against their twins and
# finite differences. Mesa's software Vulkan driver is slow, so the pipeline-level tests stay on cpu / cuda.
VULKAN_CASE = ("taichi", "vulkan")
VULKAN_MODULES = ("test_backend.py", "test_icp_kernels.py", "test_raster.py", "test_raster_binning.py")
# Known GPU failures, reported as xfail only when the test fails with exactly this error (any other failure,
# e.g. a mismatch with the twin, still fails). Delete an entry once its cause is fixed; see docs/gpu.md.
VULKAN_KNOWN: dict[str, tuple[str, str]] = {}  # test module -> (exact error text, reason) known on Vulkan


def pytest_generate_tests(metafunc):
    """Parametrise the `backend` fixture over the device matrix (+ taichi-vulkan in VULKAN_MODULES)."""
    if "backend" in metafunc.fixturenames:
        cases = list(BACKEND_CASES)
        if Path(str(metafunc.definition.path)).name in VULKAN_MODULES:
            cases.append(VULKAN_CASE)
        metafunc.parametrize("backend", cases, ids=[f"{b}-{d}" for b, d in cases], indirect=True)


@pytest.fixture
def backend(request):
    """Selects each backend on each device in turn; yields kernels.Backend. CUDA cases skip without a CUDA
    device, Vulkan cases where no Vulkan driver loads (Makefile: mesa-vulkan-drivers, libvulkan1), any case
    whose backend does not load here (kernels.devices())."""
    from swarmsplat import kernels

    name, device = request.param
    if device == "cuda" and not kernels.cuda_available():
        pytest.skip("no CUDA device on this machine")
    if kernels.Backend(name, device) not in _working_devices():
        if device == "vulkan":
            pytest.skip("no Vulkan driver loads on this machine")
        pytest.skip(f"{name} does not load on {device} here (not installed?)")  # e.g. no Taichi wheel on a Jetson
    return kernels.use(name, device)


@functools.lru_cache(maxsize=1)
def _working_devices():
    from swarmsplat import kernels

    return tuple(kernels.devices())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    known = VULKAN_KNOWN.get(Path(str(item.path)).name)
    spec = getattr(item, "callspec", None)
    if (known and rep.failed and call.excinfo is not None and spec is not None
            and spec.params.get("backend") == VULKAN_CASE and known[0] in str(call.excinfo.value)):
        rep.outcome, rep.wasxfail = "skipped", known[1]


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data; skips the calling test cleanly when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared dataset not present: {p}")
    return p


@pytest.fixture(scope="module")
def one_torch_thread():
    """Hold torch to one intra-op thread for a module of tiny tensors (thread wake-ups cost more than the work).

    Use with `pytestmark = pytest.mark.usefixtures("one_torch_thread")`.
    """
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module", params=[0, 3], ids=["seed0", "seed3"])
def default_world(request):
    """The generator's default world (6 agents) for two seeds: (world, GeneratorConfig, per-agent poses)."""
    from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, generate_world

    cfg = GeneratorConfig.preset("default", agents=6, seed=request.param)
    world = generate_world(cfg.seed, cfg.world)
    return world, cfg, agent_poses(world, cfg)
