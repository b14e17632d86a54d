"""Shared fixtures: the backend x device matrix (CUDA cases skip without a GPU) and ../shared/data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", REPO.parent / "shared" / "data"))

BACKEND_CASES = [("warp", "cpu"), ("taichi", "cpu"), ("warp", "cuda"), ("taichi", "cuda")]


@pytest.fixture(params=BACKEND_CASES, ids=[f"{b}-{d}" for b, d in BACKEND_CASES])
def backend(request):
    """Selects each backend on each device in turn; yields kernels.Backend."""
    import kernels

    name, device = request.param
    if device == "cuda" and not kernels.cuda_available():
        pytest.skip("no CUDA device on this machine")
    return kernels.use(name, device)


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
