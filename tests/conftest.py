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
