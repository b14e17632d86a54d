"""Render a set of Gaussians from a camera pose through `kernels.rasterize` (or its twin), and the eq.-3 loss
that mapping and tracking share."""

from __future__ import annotations

import numpy as np
import torch

from swarmsplat.kernels.camera import PinholeCamera

from .gaussian_map import GaussianParams
from .param_ops import Activated, activate

NEAR, FAR = 0.01, 100.0


def viewmat_from_pose(T_local_cam: np.ndarray, device="cpu", dtype=torch.float32) -> torch.Tensor:
    """[4, 4] world(local)-to-camera matrix the rasteriser takes, from a camera-to-local pose."""
    from swarmsplat.kernels import se3

    return torch.as_tensor(se3.inverse(T_local_cam), dtype=dtype, device=device)


def render(params: GaussianParams, viewmat: torch.Tensor, camera: PinholeCamera, *,
           background: tuple[float, float, float] = (0.0, 0.0, 0.0), activated: Activated | None = None):
    """Rasterise `params` seen through `viewmat` [4, 4] (local-to-camera; may carry a pose gradient).
    `activated`: `slam.dense.param_ops.activate(params)` when the caller has it already (mapping: its isotropic penalty
    goes into the loss); made here otherwise.

    Returns the rasteriser's RenderOutput (color [H, W, 3], depth [H, W] alpha-weighted metres, alpha [H, W], ...;
    n_touched is None from the kernels: nothing here uses it).
    Inside `kernels.use_reference()` the slow torch twin renders (tests).
    """
    from swarmsplat.kernels import reference_active

    extra = {}
    if reference_active():
        from swarmsplat.kernels.reference import rasterize_reference as rasterize
    else:
        from swarmsplat.kernels import rasterize

        extra["count_touched"] = False  # the pipeline does not use n_touched (None)
    dev, dt = params.means.device, params.means.dtype
    K = torch.as_tensor(camera.K, dtype=dt, device=dev)
    a = activated if activated is not None else activate(params)
    return rasterize(params.means, params.quats, a.scales, a.opacities, a.colors,
                     viewmat.to(dt), K, int(camera.width), int(camera.height),
                     background=torch.tensor(background, dtype=dt, device=dev), near=NEAR, far=FAR, **extra)


def masked_median(values: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """torch.median of values[mask] (the lower of the two middle values; NaN if any value is NaN), as a 0-dim
    tensor of values' dtype; mask must select at least one value. On the CPU through NumPy's selection: boolean
    indexing and torch.median cost ~0.36 + 0.47 ms on a 320x240 error image there, NumPy ~0.15 ms in all."""
    if values.device.type != "cpu":
        return (values if mask is None else values[mask]).median()
    a = values.detach().reshape(-1).numpy()
    a = a[mask.reshape(-1).numpy()] if mask is not None else a.copy()
    if a.size == 0:
        raise ValueError("masked_median: the mask selects no value")
    k = (a.size - 1) // 2
    a.partition(k)
    v = a[k] if not np.isnan(a).any() else np.nan
    return torch.tensor(v, dtype=values.dtype)


def rgbd_loss(out, color: torch.Tensor, depth: torch.Tensor, *, lambda_color: float, alpha_power: float,
              alpha_min: float = 0.0, inlier_k: float | None = None, normalise: bool = False) -> torch.Tensor:
    """Eq. 3: sum M_in M_alpha (λ_c |Î - I|_1 + (1 - λ_c) |D̂ - D|_1), normalised by the mask's weight.

    color [H, W, 3] in [0, 1]; depth [H, W] metres with 0 = invalid (no depth term there). M_alpha = alpha^p
    (detached, so the mask does not push alpha down); pixels with alpha < alpha_min are dropped. M_in drops pixels
    whose colour or depth error exceeds inlier_k x that frame's median error. `normalise` compares colour / alpha
    and depth / alpha (black background assumed), so the soft edge of the model does not bias a pose.
    """
    alpha = out.alpha.detach()
    valid_d = depth > 0
    if normalise:
        a = out.alpha.clamp_min(1e-3)
        r_c, r_d = out.color / a[..., None], out.depth_normalised
    else:
        r_c, r_d = out.color, out.depth
    e_c = (r_c - color).abs().mean(-1)
    e_d = (r_d - depth).abs() * valid_d
    m = alpha.clamp(0.0, 1.0) ** alpha_power if alpha_power > 0 else torch.ones_like(alpha)
    if alpha_min > 0:
        m = m * (alpha >= alpha_min)
    if inlier_k is not None:
        with torch.no_grad():
            sel = m > 0
            if bool(sel.any()):
                mc = masked_median(e_c, sel)
                md = masked_median(e_d, sel & valid_d) if bool((sel & valid_d).any()) else torch.tensor(0.0)
                inl = (e_c.detach() <= inlier_k * mc + 1e-6) & (e_d.detach() <= inlier_k * md + 1e-6)
                m = m * inl
    w = m.sum().clamp_min(1.0)
    return (m * (lambda_color * e_c + (1.0 - lambda_color) * e_d)).sum() / w


class _Eq3Loss(torch.autograd.Function):
    """rgbd_loss's rules (normalise=False, alpha_min=0) in kernel passes (kernels/_<backend>/loss.py) and two torch
    medians; the backward is one more kernel pass."""

    @staticmethod
    def forward(ctx, r_c, r_d, alpha, color, depth, lambda_color, alpha_power, inlier_k, impl, device):
        h, w = depth.shape
        dev = depth.device
        flat = lambda t: t.detach().contiguous()  # noqa: E731
        r_c, r_d, alpha, color, depth = (flat(t) for t in (r_c, r_d, alpha, color, depth))
        e_c, e_d, m0, mask = (torch.empty(h * w, dtype=torch.float32, device=dev) for _ in range(4))
        impl.errors(r_c, color, r_d, depth, alpha, alpha_power, e_c, e_d, m0, device)
        thr_c = thr_d = float("inf")
        if inlier_k is not None:
            valid = depth.reshape(-1) > 0
            sel = None if alpha_power <= 0 else m0 > 0  # alpha^0 = 1 everywhere
            if sel is None or bool(sel.any()):
                mc = masked_median(e_c, sel)
                sv = valid if sel is None else sel & valid
                md = masked_median(e_d, sv) if bool(sv.any()) else torch.tensor(0.0)
                thr_c, thr_d = float(inlier_k * mc + 1e-6), float(inlier_k * md + 1e-6)
        lam_d = float(torch.tensor(1.0 - lambda_color, dtype=torch.float32))  # as torch rounds the Python scalar
        row_sums = torch.empty(h, 2, dtype=torch.float32, device=dev)
        impl.masked_sums(e_c, e_d, m0, w, lambda_color, lam_d, thr_c, thr_d, row_sums, mask, device)
        sw, sl = row_sums.sum(0).tolist()
        ctx.weight = max(sw, 1.0)
        ctx.save_for_backward(r_c, color, r_d, depth, mask)
        ctx.args = (lambda_color, lam_d, impl, device)
        return torch.tensor(sl / ctx.weight, dtype=torch.float32, device=dev)

    @staticmethod
    def backward(ctx, g):
        r_c, color, r_d, depth, mask = ctx.saved_tensors
        lam, lam_d, impl, device = ctx.args
        s = float(g / ctx.weight)  # float32, as autograd's DivBackward
        g_c, g_d = torch.empty_like(r_c), torch.empty_like(r_d)
        impl.grads(r_c, color, r_d, depth, mask, s, lam, lam_d, g_c.view(-1), g_d.view(-1), device)
        return (g_c, g_d) + (None,) * 8


def rgbd_loss_fused(out, color: torch.Tensor, depth: torch.Tensor, *, lambda_color: float, alpha_power: float,
                    inlier_k: float | None = None) -> torch.Tensor:
    """`rgbd_loss` (normalise=False, alpha_min=0: the mapping loss) on the active kernel backend: per-pixel work
    in two kernels instead of ~40 torch operations and their autograd graph; same value and gradients.
    Falls back to `rgbd_loss` for tensors that are not float32."""
    if not all(t.dtype == torch.float32 for t in (out.color, out.depth, color, depth)):
        return rgbd_loss(out, color, depth, lambda_color=lambda_color, alpha_power=alpha_power, inlier_k=inlier_k)
    from swarmsplat import kernels

    b = kernels.active()
    return _Eq3Loss.apply(out.color, out.depth, out.alpha, color, depth, float(lambda_color), float(alpha_power),
                          None if inlier_k is None else float(inlier_k), kernels.backend_module("loss"), b.device)
