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
    # Both codes evaluate the same float32 formulas in a different order (the vector one vectorised and
    # FMA-contracted by LLVM for the host CPU), so they agree to a few roundings of each formula's largest
    # intermediate term, not bit for bit; the bounds below are stated that way (eps = 2^-24) and hold on any
    # x86-64 CPU, whichever vector width and contraction its compiled code uses.
    eps = 2.0**-24
    vis = r_s > 0
    # mean2d = f x / z + c: its terms are up to f |m| / z, |c| and |u| itself (16 roundings; 2.1 measured).
    z = p_s[:, 9].double().abs().clamp(min=1e-6)
    err_u = []
    for c, (f, cc) in enumerate(((float(K[0, 0]), float(K[0, 2])), (float(K[1, 1]), float(K[1, 2])))):
        err_u.append(16 * eps * (p_s[:, c].double().abs() + cc + f * s["means"].double().norm(dim=1) / z))
        assert ((p_v[:, c] - p_s[:, c]).double().abs() <= err_u[c])[vis].all(), c
    # The conic inverts the 2D covariance (a b; b c), whose determinant ac - b^2 cancels: each entry's error is the
    # covariance's (a few dozen roundings from quaternion and scales) times kappa = (ac + b^2) / (ac - b^2), which
    # the conic shares (1 to ~500 here); 64 roundings (12 measured), at the scale of the row's largest entry.
    A, B, C = (p_s[:, j].double() for j in (2, 3, 4))
    kappa = (A * C + B * B) / (A * C - B * B)
    row = p_s[:, 2:5].double().abs().amax(1)
    d_conic = (p_v[:, 2:5] - p_s[:, 2:5]).double().abs().amax(1)
    assert (d_conic <= 64 * eps * kappa * row)[vis].all(), float((d_conic / (eps * kappa * row))[vis].max())
    cols = [5, 6, 7, 8, 9]  # opacity and colour (copied), depth (one product and sum: 1e-5 is > 100 roundings)
    assert torch.allclose(p_v[:, cols], p_s[:, cols], rtol=1e-5, atol=1e-5)
    assert torch.equal(t_v, t_s)  # the skip threshold -log(255 o) - 1e-5: the same scalar ops on the opacity
    # The integer outputs floor or ceil float ones: radius = ceil(3 sqrt(lambda_max)), the tile rectangle
    # floor((mx -+ r) / 16) cut to ceil / floor(mx -+ ex) of the alpha >= 1/255 ellipse. Where one of those lies
    # within the rounding above of an integer the two codes may land on neighbouring integers (a flip, as at the
    # rasteriser's cut-off), by CPU. Exact equality is asserted away from that; the few Gaussians near an integer
    # may differ by one. The float64 recomputation from the scalar outputs carries the conic's error too.
    assert torch.equal(n_s < 0, n_v < 0)  # invalid-input flags: NaN / range tests, no rounding
    det = A * C - B * B
    a, cv = C / det, A / det  # the covariance's diagonal
    mid = 0.5 * (a + cv)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - a * cv + (B / det) ** 2, min=0.1))
    lgm = (-1.01 * t_s.double() + 0.01).clamp(min=0)
    ex, ey = torch.sqrt(2 * lgm * a), torch.sqrt(2 * lgm * cv)
    mx, my, r = p_s[:, 0].double(), p_s[:, 1].double(), r_s.double()
    # (value, its float32 error): r and ex, ey carry the covariance's error (64 eps kappa, relative), mx, my the
    # mean2d's; the tile edges divide by 16 exactly.
    r3 = 3 * torch.sqrt(lam)
    edges = [(r3, 64 * eps * kappa * r3), ((mx - r) / 16, err_u[0] / 16), ((mx + r) / 16, err_u[0] / 16),
             ((my - r) / 16, err_u[1] / 16), ((my + r) / 16, err_u[1] / 16)]
    edges += [(mx + sg * ex, err_u[0] + 64 * eps * kappa * ex) for sg in (-1, 1)]
    edges += [(my + sg * ey, err_u[1] + 64 * eps * kappa * ey) for sg in (-1, 1)]
    near = torch.zeros(N, dtype=torch.bool)
    for e, err in edges:
        near |= ((e - e.round()).abs() < err) & vis
    assert int(near.sum()) <= N // 50, int(near.sum())  # a handful of Gaussians, not a systematic difference
    far = ~near
    assert torch.equal(n_s[far], n_v[far]) and torch.equal(r_s[far], r_v[far]) and torch.equal(rc_s[far], rc_v[far])
    assert int((r_s - r_v).abs().max()) <= 1 and int((rc_s - rc_v).abs().max()) <= 1
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
