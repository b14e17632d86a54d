"""The CPU's vector projection (kernels/_warp/project_cpu.py) against Warp's scalar projection kernels (the CUDA
ones, kernels/_warp/project.py): every forward output, the invalid-input flags and all gradients, viewmat included,
over several blocks with a ragged tail."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError

W, H = 70, 52
K = torch.tensor([[58.0, 0.0, W / 2 - 0.6], [0.0, 57.0, H / 2 + 0.3], [0.0, 0.0, 1.0]])
N = 700  # 3 CPU blocks of 256 (the last ragged), each in sub-blocks of 64 (ragged too)


def _scene(seed: int = 3) -> dict:
    g = torch.Generator().manual_seed(seed)
    z = torch.empty(N).uniform_(0.3, 6.0, generator=g)
    z[:20] = torch.empty(20).uniform_(-2.0, -0.1, generator=g)  # behind the camera
    z[20:30] = 0.004  # nearer than `near`
    xy = torch.randn(N, 2, generator=g) * 0.6 * z[:, None]
    xy[30:80] *= 4.0  # off-screen: the field-of-view clamp is active
    means = torch.cat([xy, z[:, None]], 1)
    scales = torch.exp(torch.empty(N, 3).uniform_(-6.0, -1.0, generator=g))
    scales[80:90] = 2.0  # cover the image
    return dict(means=means, quats=torch.randn(N, 4, generator=g), scales=scales,
                opacities=torch.rand(N, generator=g), colors=torch.rand(N, 3, generator=g))


def _viewmat() -> torch.Tensor:
    return torch.tensor(se3.exp(np.array([0.05, -0.1, 0.03, 0.08, -0.04, 0.1])), dtype=torch.float32)


def _project(s: dict, vm: torch.Tensor):
    from swarmsplat.kernels._warp import project

    n = s["means"].shape[0]
    proj, pthr = torch.zeros(n, 10), torch.zeros(n)
    radius, ntiles = torch.zeros(n, dtype=torch.int32), torch.zeros(n, dtype=torch.int32)
    rect = torch.zeros(n, 4, dtype=torch.int32)
    k = K.reshape(-1).tolist()
    project.project_forward(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], vm,
                            (k[0], k[4], k[2], k[5]), W, H, 0.01, 100.0, proj, radius, rect, ntiles, pthr, "cpu")
    return proj, radius, rect, ntiles, pthr


@pytest.fixture
def modes(monkeypatch):
    from swarmsplat.kernels._warp import project

    kernels.use("warp", "cpu")

    def set_mode(mode: str) -> None:
        monkeypatch.setattr(project, "CPU_PROJECT", mode)

    return set_mode


def test_vector_projection_forward_equals_scalar(modes):
    s = _scene()
    s["means"][100, 1] = float("nan")
    s["quats"][101] = 0.0
    s["opacities"][102] = 1.5
    s["colors"][103, 2] = float("inf")
    out = {}
    for mode in ("scalar", "vector"):
        modes(mode)
        out[mode] = _project(s, _viewmat())
    (p_s, r_s, rc_s, n_s, t_s), (p_v, r_v, rc_v, n_v, t_v) = out["scalar"], out["vector"]
    assert (n_s == -1).sum() == 4 and (n_s > 0).sum() > N // 2 and (n_s == 0).sum() > 30
    assert torch.equal(n_s, n_v) and torch.equal(r_s, r_v) and torch.equal(rc_s, rc_v)
    cols = [0, 1, 5, 6, 7, 8, 9]  # mean2d, opacity, colour, depth; the conic (2-4) inverts a cancelling determinant
    assert torch.allclose(p_v[:, cols], p_s[:, cols], rtol=1e-5, atol=1e-5)
    assert torch.allclose(p_v[:, 2:5], p_s[:, 2:5], rtol=3e-4, atol=1e-5)
    assert torch.allclose(t_v, t_s, rtol=1e-6, atol=1e-6)
    culled = r_v == 0
    assert not p_v[culled].any() and not t_v[culled].any() and not rc_v[culled].any() and (n_v[culled] <= 0).all()


def test_tile_rectangles_are_the_radius_rectangles_cut_to_the_alpha_ellipse(modes):
    """The listed tiles: inside the 3-sigma radius' rectangle, and for low opacities far fewer (the box of the
    alpha >= 1/255 ellipse); renders against the twin with these lists are tests/test_raster.py's."""
    s = _scene()
    s["opacities"][:350] *= 0.05  # faint: their alpha >= 1/255 ellipse is well inside 3 sigma
    for mode in ("scalar", "vector"):
        modes(mode)
        proj, radius, rect, ntiles, _ = _project(s, _viewmat())
        vis = radius > 0
        r = radius.float()
        ntx, nty = (W + 15) // 16, (H + 15) // 16
        box = torch.stack([((proj[:, 0] - r) / 16).floor().clamp(0, ntx), ((proj[:, 1] - r) / 16).floor().clamp(0, nty),
                           ((proj[:, 0] + r) / 16).floor().add(1).clamp(0, ntx),
                           ((proj[:, 1] + r) / 16).floor().add(1).clamp(0, nty)], 1).int()
        listed = vis & (ntiles > 0)
        assert (rect[listed, :2] >= box[listed, :2]).all() and (rect[listed, 2:] <= box[listed, 2:]).all()
        assert torch.equal(ntiles[vis], ((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1]))[vis])
        full = (box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])
        faint = vis.clone()
        faint[350:] = False
        assert ntiles[faint].sum() < 0.7 * full[faint].sum(), mode
        assert (vis & (ntiles == 0)).any(), mode  # visible, but no tile reaches alpha 1/255


def test_vector_projection_flags_invalid_input(modes):
    modes("vector")
    s = _scene()
    s["quats"][5] = 0.0
    p = dict(**s, viewmat=_viewmat(), K=K, width=W, height=H)
    with pytest.raises(InputError, match="quats"):
        kernels.rasterize(**p)


def test_vector_projection_gradients_equal_scalar(modes):
    s = _scene()
    wts = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(4))
    results = {}
    for mode in ("scalar", "vector"):
        modes(mode)
        p = {k: v.clone().requires_grad_(True) for k, v in s.items()}
        vm = _viewmat().requires_grad_(True)
        out = kernels.rasterize(**p, viewmat=vm, K=K, width=W, height=H)
        ((out.color * wts).sum() + 0.3 * out.depth.sum() + out.alpha.sum()).backward()
        results[mode] = ({k: v.grad for k, v in p.items()}, vm.grad, out)
    (g_s, v_s, o_s), (g_v, v_v, o_v) = results["scalar"], results["vector"]
    assert torch.allclose(o_v.color, o_s.color, atol=2e-5)
    for k in g_s:
        assert g_s[k].abs().max() > 0, k
        assert torch.allclose(g_v[k], g_s[k], rtol=1e-4, atol=1e-4 * g_s[k].abs().max().item()), k
    assert torch.allclose(v_v, v_s, rtol=1e-4, atol=1e-4 * v_s.abs().max().item())
    culled = o_v.radii == 0
    assert culled.sum() > 30 and not g_v["means"][culled].any() and not g_v["quats"][culled].any()
