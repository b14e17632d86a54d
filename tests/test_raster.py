"""The Gaussian rasteriser against its dense twin, finite differences, and the other backend.

Precision plan: the Warp/Taichi kernels are float32 only, so finite differences are taken on the float64 twin
(kernels.reference.rasterize_reference, which implements the same rules densely and gets its gradients from
autograd). The chain is then: FD(twin, float64) == autograd(twin) to 1e-6, and kernels == autograd(twin) to
float32 accuracy (relative 5e-4 of the largest gradient entry). The pose gradient is checked the same way with
central differences on SE(3): viewmat = exp(+-eps e_i) @ viewmat0. Every kernel output and scratch buffer is
poisoned (NaN / -7) before each run, so an unwritten pixel or entry shows up.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import raster, se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.reference import rasterize_reference

from raster_scenes import H, K, W, poison, scene, viewmat_rotated, viewmat_translation  # noqa: F401 (poison: autouse)

# Tiny tensors: torch's intra-op threads only add wake-up latency on a busy 2-core machine.
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _near_cutoffs(s, viewmat, K, w, h, rel=1e-5):
    """Where float32 rounding may decide a discontinuity of the compositing rules, found with the float64 twin's
    projection: pixels [H, W] where some Gaussian's power lies within `rel` of the 1/255 cut-off log(1/255 / o)
    or the transmittance within `rel` of the 1e-4 floor, per-Gaussian counts [N] of such pixels, and the
    Gaussians whose radius 3 sqrt(lambda_max) lies within `rel` of an integer. `rel` is relative to the power's
    largest term times the conic's condition kappa = (AC + B^2) / (AC - B^2) (the conic inverts a cancelling
    determinant, so two codes' conics differ by ~kappa roundings): 1e-5 is > 100 float32 roundings of them.
    Two float32 codes may disagree there (a Gaussian composited or not: colour and alpha move by up to 1/255),
    by CPU; everywhere else they agree to rounding."""
    from swarmsplat.kernels._ref_raster import ALPHA_MAX, ALPHA_MIN, T_MIN, project_reference

    p = {k: v.double() for k, v in s.items()}
    mean2d, conic, z, radius, rect, vis = project_reference(p["means"], p["quats"], p["scales"], viewmat.double(),
                                                             K.double(), w, h, 0.01, 100.0)
    A, B, C = conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]
    kappa = ((A * C + B * B) / (A * C - B * B)).abs()
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    dx, dy = xs.reshape(-1, 1) - mean2d[:, 0], ys.reshape(-1, 1) - mean2d[:, 1]
    quad, cross = 0.5 * (A * dx * dx + C * dy * dy), B * dx * dy
    power = -quad - cross
    tol = rel * kappa * (quad.abs() + cross.abs() + 1.0)
    lo = torch.log(ALPHA_MIN / p["opacities"])
    near = vis & ((power - lo).abs() < tol)  # [P, N]
    alpha = torch.where(vis & (power >= lo), (p["opacities"] * torch.exp(power.clamp(max=0))).clamp(max=ALPHA_MAX), 0)
    order = torch.sort(torch.where(vis, z, torch.full_like(z, math.inf)), stable=True).indices
    t = torch.cumprod(1 - alpha[:, order], dim=1)
    near_t = ((t / T_MIN - 1).abs() < rel * (torch.arange(len(z)) + 1)).any(1)  # each layer's rounding adds up
    pixels = (near.any(1) | near_t).reshape(h, w)
    cov = torch.linalg.inv(conic)
    mid = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    r3 = 3 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - torch.linalg.det(cov), min=0.1)))
    radius_near = vis & ((r3 - r3.round()).abs() < rel * kappa * r3)
    return pixels, near.sum(0), radius_near


def _assert_equal_but_cutoff_flips(a, b, hazard, pairs, depth_atol, rtol=0.0, atol=1e-5):
    """Two renders of one scene by two float32 codes: colour, alpha within atol (+ rtol) and depth within depth_atol
    outside `hazard` (see _near_cutoffs); at hazard pixels within the cut-off's bound, a Gaussian of alpha <= 1/255
    composited or not (it and the transmittance it takes from those behind: 2 / 255 of colour, alpha, and of the
    farthest depth); per Gaussian, n_touched differs by at most its hazard pixels."""
    from swarmsplat.kernels._ref_raster import ALPHA_MIN

    ok = ~hazard
    for f, tol in (("color", atol), ("alpha", atol), ("depth", depth_atol)):
        x, y = getattr(a, f), getattr(b, f)
        assert torch.allclose(x[ok], y[ok], atol=tol, rtol=rtol), f
        bound = 2 * ALPHA_MIN * (float(y.max()) if f == "depth" else 1.0)
        assert bool(((x - y).abs()[hazard] <= bound).all()), f
    assert bool(((a.n_touched - b.n_touched).abs() <= pairs).all())


def render_both(s, viewmat, background=None):
    out = kernels.rasterize(**s, viewmat=viewmat, K=K, width=W, height=H, background=background)
    ref = rasterize_reference(**{k: v.double() for k, v in s.items()}, viewmat=viewmat.double(), K=K.double(),
                              width=W, height=H, background=None if background is None else background.double())
    return out, ref


def assert_forward_matches(out, ref):
    for name in ("color", "depth", "alpha"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.dtype == torch.float32 and a.shape == b.shape
        assert torch.isfinite(a).all(), f"{name} has unwritten (NaN) pixels"
        err = (a.double() - b).abs().max().item()
        assert err < 1e-4, f"{name}: max abs error {err}"
    ok = ref.alpha > 0.05  # depth / alpha amplifies float32 rounding where alpha is tiny
    assert torch.isfinite(out.depth_normalised).all()
    err = (out.depth_normalised.double() - ref.depth_normalised).abs()
    assert torch.where(ok, err, torch.zeros_like(err)).max().item() < 1e-3
    assert torch.equal(out.radii, ref.radii)
    assert torch.equal(out.n_touched, ref.n_touched)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_matches_twin_on_hard_scenes(backend, seed):
    s = scene(seed)
    out, ref = render_both(s, viewmat_translation(seed), background=torch.tensor([0.1, 0.6, 0.3]))
    assert_forward_matches(out, ref)
    # The scene really exercises what it claims: culled ones, huge ones, and something drawn.
    assert (ref.radii == 0).sum() >= 6 and ref.radii.max() > 40 and ref.alpha.max() > 0.5


def test_forward_matches_twin_with_rotation(backend):
    s = scene(5, n_plain=60, hard=False)
    out, ref = render_both(s, viewmat_rotated())
    assert_forward_matches(out, ref)


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_gaussian(backend, n):
    s = scene(3, n_plain=n, hard=False)
    if n == 1:
        s["means"][0] = torch.tensor([0.1, -0.1, 2.0])
        s["scales"][0] = torch.tensor([0.3, 0.2, 0.1])
        s["opacities"][0] = 0.8
    bg = torch.tensor([0.25, 0.5, 0.75])
    out, ref = render_both(s, torch.eye(4), background=bg)
    assert_forward_matches(out, ref)
    if n == 0:
        assert torch.equal(out.color, bg.expand(H, W, 3)) and not out.alpha.any() and not out.depth.any()
    else:
        assert out.alpha.max() > 0.3 and out.radii[0] > 0 and out.n_touched[0] > 0


def test_saturated_pixels_stop_at_transmittance_floor(backend):
    # Many opaque layers: compositing must stop before T < 1e-4, as the twin does.
    g = torch.Generator().manual_seed(9)
    n = 30
    s = dict(means=torch.cat([torch.zeros(n, 2), torch.linspace(2, 3, n)[:, None]], 1),
             quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), scales=torch.full((n, 3), 0.5),
             opacities=torch.full((n,), 0.98), colors=torch.rand(n, 3, generator=g))
    out, ref = render_both(s, torch.eye(4))
    assert_forward_matches(out, ref)
    assert ref.alpha.max() > 0.999 and (ref.n_touched < ref.n_touched[0]).any()


def _loss_weights(seed: int):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(H, W, 3, generator=g), torch.rand(H, W, generator=g), torch.rand(H, W, generator=g),
            torch.rand(H, W, generator=g)]


def _loss(out, w):
    return ((out.color * w[0].to(out.color)).sum() + (out.depth * w[1].to(out.depth)).sum()
            + (out.alpha * w[2].to(out.alpha)).sum() + (out.depth_normalised * w[3].to(out.depth)).sum())


NAMES = ("means", "quats", "scales", "opacities", "colors")


def _grads(fn, s, viewmat0, bg, dtype):
    """Gradients of the weighted loss to the Gaussians and to the twist xi of viewmat = exp(xi) @ viewmat0."""
    params = {k: v.to(dtype).clone().requires_grad_(True) for k, v in s.items()}
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    bg = bg.detach().to(dtype).clone().requires_grad_(True)
    viewmat = (se3.exp_torch(xi) @ viewmat0.double()).to(dtype)
    out = fn(**params, viewmat=viewmat, K=K.to(dtype), width=W, height=H, background=bg)
    _loss(out, _loss_weights(7)).backward()
    grads = {k: p.grad.double() for k, p in params.items()}
    grads["background"] = bg.grad.double()
    return grads, xi.grad


def _twin_loss(s, viewmat, bg):
    out = rasterize_reference(**s, viewmat=viewmat, K=K.double(), width=W, height=H, background=bg)
    return _loss(out, _loss_weights(7)).item()


def _grad_scene():
    s = scene(11, n_plain=25, hard=True)
    s["opacities"] = s["opacities"].clamp(max=0.9)  # keep away from the 0.99 clamp where FD has a kink
    return s


def test_gradients_match_twin_autograd(backend):
    s, v0, bg = _grad_scene(), viewmat_rotated(), torch.tensor([0.3, 0.2, 0.7])
    g_k, xi_k = _grads(kernels.rasterize, s, v0, bg, torch.float32)
    g_r, xi_r = _grads(rasterize_reference, s, v0, bg, torch.float64)
    for name in NAMES + ("background",):
        scale = g_r[name].abs().max().item()
        assert scale > 0, name
        err = (g_k[name] - g_r[name]).abs().max().item()
        assert err <= 5e-4 * scale, f"d/d{name}: max abs error {err} vs max {scale}"
    assert (xi_k - xi_r).abs().max().item() <= 5e-4 * xi_r.abs().max().item(), (xi_k, xi_r)


@functools.lru_cache(maxsize=1)
def _finite_differences():
    """Central differences of the float64 twin's loss: ((name, direction, fd), ...) for random directions of each
    Gaussian parameter, and fd [6] along SE(3) twists (left perturbation in the camera frame). Computed once."""
    s, v0, bg = _grad_scene(), viewmat_rotated().double(), torch.tensor([0.3, 0.2, 0.7], dtype=torch.float64)
    s64 = {k: v.double() for k, v in s.items()}
    eps = 1e-6
    gen = torch.Generator().manual_seed(3)
    directional = []
    for name in NAMES:
        u = torch.randn(s64[name].shape, generator=gen, dtype=torch.float64)
        plus, minus = dict(s64), dict(s64)
        plus[name], minus[name] = s64[name] + eps * u, s64[name] - eps * u
        directional.append((name, u, (_twin_loss(plus, v0, bg) - _twin_loss(minus, v0, bg)) / (2 * eps)))
    pose = []
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        pose.append((_twin_loss(s64, torch.tensor(se3.exp(d)) @ v0, bg)
                     - _twin_loss(s64, torch.tensor(se3.exp(-d)) @ v0, bg)) / (2 * eps))
    return tuple(directional), torch.tensor(pose, dtype=torch.float64)


def test_twin_autograd_matches_finite_differences():
    s, v0, bg = _grad_scene(), viewmat_rotated(), torch.tensor([0.3, 0.2, 0.7])
    g_r, xi_r = _grads(rasterize_reference, s, v0, bg, torch.float64)
    directional, pose = _finite_differences()
    for name, u, fd in directional:
        assert abs((g_r[name] * u).sum().item() - fd) <= 1e-5 * (1 + abs(fd)), (name, fd)
    assert torch.allclose(xi_r, pose, rtol=1e-5, atol=1e-5), (xi_r, pose)


def test_gradients_match_finite_differences(backend):
    s, v0, bg = _grad_scene(), viewmat_rotated(), torch.tensor([0.3, 0.2, 0.7])
    g_k, xi_k = _grads(kernels.rasterize, s, v0, bg, torch.float32)
    directional, pose = _finite_differences()
    for name, u, fd in directional:
        assert abs((g_k[name] * u).sum().item() - fd) <= 1e-3 * (1 + abs(fd)), (name, fd)
    for i in range(6):
        assert abs(xi_k[i].item() - pose[i].item()) <= 1e-3 * (1 + abs(pose[i].item())), (i, pose, xi_k)


def test_twist_gradient_closed_form(backend):
    s, v0 = scene(4, n_plain=20, hard=False), viewmat_rotated()
    _, xi_auto = _grads(kernels.rasterize, s, v0, torch.zeros(3), torch.float32)
    vm = v0.clone().requires_grad_(True)
    out = kernels.rasterize(**s, viewmat=vm, K=K, width=W, height=H)
    _loss(out, _loss_weights(7)).backward()
    xi_closed = raster.twist_gradient(vm.grad.double(), v0.double())
    assert torch.allclose(xi_closed, xi_auto, rtol=1e-4, atol=1e-4 * xi_auto.abs().max().item())


def test_warp_equals_taichi():
    g = torch.Generator().manual_seed(21)
    n, w, h = 400, 80, 56  # 5 x 4 tiles, ragged edges
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 3, 2 + 3 * torch.rand(n, 1, generator=g)], 1)
    params = dict(means=means, quats=torch.randn(n, 4, generator=g), scales=0.01 + 0.1 * torch.rand(n, 3, generator=g),
                  opacities=torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g))
    Kb = torch.tensor([[60.0, 0, 39.5], [0, 60.0, 27.5], [0, 0, 1]])
    # The few pixels where rounding decides whether a Gaussian is composited (3 of 4480 here) are left out of the
    # loss and held to the cut-off's bound only; no radius is within rounding of an integer, so radii are equal.
    hazard, pairs, radius_near = _near_cutoffs(params, viewmat_rotated(), Kb, w, h)
    assert hazard.float().mean() < 0.01 and not radius_near.any()
    keep = (~hazard).float()
    results = {}
    for name in ("warp", "taichi"):
        kernels.use(name, "cpu")
        p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
        vm = viewmat_rotated().requires_grad_(True)
        out = kernels.rasterize(**p, viewmat=vm, K=Kb, width=w, height=h, background=torch.tensor([0.5, 0.5, 0.5]))
        wts = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1)) * keep[..., None]
        ((out.color * wts).sum() + (out.depth * keep).sum() + (out.alpha * keep).sum()).backward()
        results[name] = (out, {k: v.grad for k, v in p.items()}, vm.grad)
    (ow, gw, vw), (ot, gt, vt) = results["warp"], results["taichi"]
    # The backends round differently (their own power expression, exp and, per CPU, FMA contraction): each layer's
    # alpha differs by a few float32 roundings (~1e-6 relative after the cancelling quadratic form), and a pixel
    # composites tens of layers, so alpha and colour (both <= 1) differ by up to ~100 roundings, 1e-5 (3.5e-6 and
    # 1.7e-6 measured). Depth = sum of w_i z_i carries the same weights' error times z: its bound is 1e-5 of the
    # farthest depth, not an absolute 1e-5 (1.1e-5 measured at 1.1 m, with depths to 3.9 m).
    _assert_equal_but_cutoff_flips(ow, ot, hazard, pairs, depth_atol=1e-5 * float(ot.depth.max()))
    assert torch.equal(ow.radii, ot.radii)
    for k in gw:
        assert torch.allclose(gw[k], gt[k], rtol=1e-4, atol=1e-4 * gt[k].abs().max().item()), k
    assert torch.allclose(vw, vt, rtol=1e-4, atol=1e-4 * vt.abs().max().item())


@pytest.mark.parametrize("name", ["warp", "taichi"])
@pytest.mark.parametrize("n_plain, w, h", [(60, 45, 37), (900, 40, 33)])  # ragged tiles; many layers: early stop
def test_cpu_vector_kernels_equal_scalar(monkeypatch, name, n_plain, w, h):
    """The CPU's vector compositing (kernels/_warp/raster_cpu.py, kernels/_taichi/raster_cpu.py) against the
    backend's scalar kernels (the GPU ones), forward outputs, per-Gaussian pair counts and all gradients, on tiles
    cut by both image edges."""
    import importlib

    backend_raster = importlib.import_module(f"swarmsplat.kernels._{name}.raster")
    s = scene(5, n_plain=n_plain, hard=True)
    Kr = torch.tensor([[36.0, 0.0, w / 2 - 0.7], [0.0, 35.0, h / 2 + 0.4], [0.0, 0.0, 1.0]])
    # The vector code has its own exp (a polynomial, 1.2e-7) and grouping of the power, so at the few pixels where
    # rounding decides the 1/255 cut-off or the transmittance floor (3 and 43 here) the two may composite different
    # Gaussians: those pixels are left out of the loss and held to the cut-off's bound (the projection, sort and
    # radii are shared code).
    hazard, pairs, _ = _near_cutoffs(s, viewmat_rotated(), Kr, w, h)
    assert hazard.float().mean() < 0.05
    keep = (~hazard).float()
    kernels.use(name, "cpu")
    results = {}
    for mode in ("scalar", "vector"):
        monkeypatch.setattr(backend_raster, "CPU_COMPOSITE", mode)
        p = {k: v.clone().requires_grad_(True) for k, v in s.items()}
        vm = viewmat_rotated().requires_grad_(True)
        out = kernels.rasterize(**p, viewmat=vm, K=Kr, width=w, height=h, background=torch.tensor([0.2, 0.5, 0.9]))
        wts = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(2)) * keep[..., None]
        ((out.color * wts).sum() + 0.3 * (out.depth * keep).sum() - (out.alpha * keep).sum()
         + 0.2 * (out.depth_normalised * keep).sum()).backward()
        results[mode] = (out, {k: v.grad for k, v in p.items()}, vm.grad)
    (o_s, g_s, v_s), (o_v, g_v, v_v) = results["scalar"], results["vector"]
    assert o_s.n_touched.sum() > 0
    for f in ("color", "depth", "alpha", "depth_normalised"):
        assert torch.isfinite(getattr(o_v, f)).all(), f
    # Outside those pixels: a few roundings per layer (2e-5 is ~100 of them at colour / depth ~1).
    _assert_equal_but_cutoff_flips(o_v, o_s, hazard, pairs, depth_atol=2e-5, rtol=1e-5, atol=2e-5)
    assert torch.allclose(o_v.depth_normalised[~hazard], o_s.depth_normalised[~hazard], atol=2e-5, rtol=1e-5)
    for k in g_s:
        assert torch.allclose(g_v[k], g_s[k], rtol=1e-4, atol=1e-4 * g_s[k].abs().max().item()), k
    assert torch.allclose(v_v, v_s, rtol=1e-4, atol=1e-4 * v_s.abs().max().item())


def _good():
    s = scene(0, n_plain=5, hard=False)
    return dict(**s, viewmat=torch.eye(4), K=K, width=W, height=H)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("means", torch.zeros(5, 2), "argument 'means': expected shape"),
        ("quats", torch.ones(4, 4), "argument 'quats': expected shape"),
        ("scales", torch.ones(5, 3, dtype=torch.float64), "argument 'scales': expected dtype"),
        ("opacities", torch.full((5,), float("nan")), "argument 'opacities': contains NaN"),
        ("opacities", torch.full((5,), 1.5), "argument 'opacities': expected values in"),
        ("means", torch.full((5, 3), float("inf")), "argument 'means': contains NaN or Inf"),
        ("scales", torch.full((5, 3), float("nan")), "argument 'scales': contains NaN or Inf"),
        ("colors", torch.full((5, 3), float("nan")), "argument 'colors': contains NaN or Inf"),
        ("quats", torch.full((5, 4), float("nan")), "argument 'quats': contains NaN or Inf"),
        ("colors", torch.ones(5, 3, dtype=torch.int32), "argument 'colors': expected dtype"),
        ("viewmat", torch.full((4, 4), float("inf")), "argument 'viewmat': contains NaN or Inf"),
        ("K", torch.eye(4), "argument 'K': expected shape"),
        ("quats", torch.zeros(5, 4), "argument 'quats': contains a zero-length"),
        ("means", torch.zeros(5, 3, device="meta"), "argument 'means': expected a tensor on cpu"),
        ("width", 0, "argument 'width'"),
        ("height", 2.5, "argument 'height'"),
        ("background", torch.ones(4), "argument 'background': expected shape"),
    ],
)
def test_bad_inputs_name_the_argument(backend, field, value, match):
    args = _good()
    args[field] = value
    with pytest.raises(InputError, match=match):
        kernels.rasterize(**args)


def test_expanded_upstream_gradients(backend):
    # sum() hands the backward stride-0 gradients; they must act like explicit ones.
    s = scene(6, n_plain=30, hard=False)
    grads = []
    for explicit in (False, True):
        p = {k: v.clone().requires_grad_(True) for k, v in s.items()}
        out = kernels.rasterize(**p, viewmat=viewmat_rotated(), K=K, width=W, height=H)
        if explicit:
            torch.autograd.backward([out.color, out.depth_normalised], [torch.ones_like(out.color), torch.ones_like(out.depth)])
        else:
            (out.color.sum() + out.depth_normalised.sum()).backward()
        grads.append({k: v.grad for k, v in p.items()})
    for k in grads[0]:
        assert torch.allclose(grads[0][k], grads[1][k], rtol=1e-6, atol=1e-7), k


def test_count_touched_off_gives_none_and_the_same_render(backend):
    s = scene(8, n_plain=40, hard=True)
    outs, grads = [], []
    for count in (True, False):
        p = {k: v.clone().requires_grad_(True) for k, v in s.items()}
        out = kernels.rasterize(**p, viewmat=viewmat_rotated(), K=K, width=W, height=H, count_touched=count)
        (out.color.sum() + out.depth.sum()).backward()
        outs.append(out)
        grads.append({k: v.grad for k, v in p.items()})
    assert outs[0].n_touched.sum() > 0 and outs[1].n_touched is None
    for f in ("color", "depth", "alpha", "depth_normalised", "radii"):
        assert torch.equal(getattr(outs[0], f), getattr(outs[1], f)), f
    for k in grads[0]:
        assert torch.equal(grads[0][k], grads[1][k]), k


def test_kernels_are_handed_no_tensor_that_requires_grad(backend):
    """Taichi gives a tensor that requires grad a .grad (a leaf) or warns (a non-leaf: the saved depth_normalised
    output) on every launch; forward and backward hand the kernels detached tensors only."""
    import warnings

    s = scene(3)
    p = {k: v.clone().requires_grad_(True) for k, v in s.items()}
    vm = viewmat_rotated().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*grad attribute.*")
        out = kernels.rasterize(**p, viewmat=vm, K=K, width=W, height=H)
        assert all(v.grad is None for v in p.values()) and vm.grad is None  # nothing allocated by the forward
        (out.color.sum() + out.depth_normalised.sum() + out.alpha.sum()).backward()
    assert all(torch.isfinite(v.grad).all() for v in p.values())
