"""The rasteriser tests' scenes (random Gaussians with the hard cases: behind the camera, off-screen, huge, tiny,
nearer than `near`, exact depth ties) and the autouse fixture that poisons every kernel output before a run, so an
unwritten pixel or entry shows up. Shared by tests/test_raster.py and tests/test_raster_binning.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat.kernels import raster, se3

W, H = 32, 24  # 2 x 2 tiles, the second column and row partly outside the image
K = torch.tensor([[30.0, 0.0, 15.3], [0.0, 28.0, 11.6], [0.0, 0.0, 1.0]])



@pytest.fixture(autouse=True)
def poison(monkeypatch):
    def _poisoned(shape, dtype, device):
        t = torch.empty(shape, dtype=dtype, device=device)
        return t.fill_(float("nan")) if dtype.is_floating_point else t.fill_(-7)

    monkeypatch.setattr(raster, "_empty", _poisoned)


def _gaussians(g: torch.Generator, n: int, z_lo: float, z_hi: float, spread: float, s_lo: float, s_hi: float):
    means = torch.empty(n, 3)
    means[:, :2] = (torch.rand(n, 2, generator=g) - 0.5) * 2 * spread
    means[:, 2] = z_lo + (z_hi - z_lo) * torch.rand(n, generator=g)
    quats = torch.randn(n, 4, generator=g) * 2.0  # not normalised on purpose
    scales = s_lo + (s_hi - s_lo) * torch.rand(n, 3, generator=g)
    return means, quats, scales


def scene(seed: int, n_plain: int = 40, hard: bool = True):
    """Random scene in front of the camera; with `hard`, also Gaussians behind the camera, off-screen, very
    large, very small, and a group overlapping at exactly the same depth. Returns a dict of float32 tensors."""
    g = torch.Generator().manual_seed(seed)
    parts = [_gaussians(g, n_plain, 1.5, 5.0, 1.2, 0.02, 0.3)]
    if hard:
        parts += [
            _gaussians(g, 4, -3.0, -0.5, 1.0, 0.05, 0.3),  # behind the camera
            _gaussians(g, 4, 2.0, 4.0, 30.0, 0.05, 0.2),  # mostly far off-screen
            _gaussians(g, 2, 2.0, 3.0, 0.5, 1.0, 2.5),  # very large: cover every tile
            _gaussians(g, 4, 1.0, 4.0, 1.0, 1e-5, 1e-4),  # very small: the 0.3 px low-pass dominates
            _gaussians(g, 2, 0.005, 0.009, 0.01, 0.01, 0.02),  # in front of the camera but nearer than `near`
        ]
        same = _gaussians(g, 4, 2.5, 2.5, 0.15, 0.05, 0.15)  # equal depth, overlapping
        parts.append(same)
    means, quats, scales = (torch.cat(p) for p in zip(*parts))
    n = means.shape[0]
    return dict(
        means=means, quats=quats, scales=scales,
        opacities=0.05 + 0.94 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
    )


def viewmat_translation(seed: int) -> torch.Tensor:
    # Pure translation keeps the equal-depth group at exactly equal z in float32 and float64 alike.
    v = torch.eye(4)
    v[:3, 3] = torch.tensor([0.05, -0.03, 0.1]) * (seed % 3)
    return v


def viewmat_rotated() -> torch.Tensor:
    return torch.tensor(se3.exp(np.array([0.08, -0.12, 0.05, 0.1, 0.05, -0.2])), dtype=torch.float32)
