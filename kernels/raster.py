"""Differentiable 3D Gaussian splatting rasteriser (the 3DGS rules), colour + depth + alpha, Warp or Taichi.

Pipeline, one call:
1. `_ProjectFn` (one kernel thread per Gaussian, hand-written backward): camera-space means, EWA 2D covariance
   with the 0.3 px low-pass, its inverse (conic), 3-sigma radius and the 16x16-tile rectangle of every Gaussian;
   culls outside near/far, off-screen and degenerate ones. Its backward gives the gradients of means, quats,
   scales and the viewmat (including the rotation's effect on the projected covariance).
2. Stable depth sort of the visible Gaussians (torch) and a packed [M, 10] attribute table in that order.
3. `_RasterFn` (hand-written forward and backward kernels on the active backend, see kernels/_warp/raster.py
   and kernels/_taichi/raster.py): a counting sort into per-tile lists (keeps depth order), per-tile
   front-to-back compositing, and reverse compositing for the gradients, per tile-entry without atomics.

The rules are spelled out in `kernels/_ref_raster.py`, the dense twin this module is tested against.
The tracking gradient: parametrise `viewmat = kernels.se3.exp_torch(xi) @ viewmat0` (left perturbation in the
camera frame, xi = [omega, v]) and autograd turns the [4, 4] viewmat gradient into dL/dxi; `twist_gradient`
does the same contraction in closed form at xi = 0.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .backend import active
from .checks import check_tensor
from .errors import InputError

TILE = 16  # pixels per tile side; the kernels hard-code the same value
PACKED = 10  # packed attribute row: mean2d x, y, conic a, b, c, opacity, r, g, b, z
DEPTH_EPS = 1e-6  # alpha below which depth_normalised is 0


class RenderOutput(NamedTuple):
    color: torch.Tensor  # [H, W, 3] composited colour plus T_final * background
    depth: torch.Tensor  # [H, W] alpha-weighted depth sum_i z_i alpha_i T_i (metres, camera z)
    depth_normalised: torch.Tensor  # [H, W] depth / alpha where alpha > 1e-6, else 0
    alpha: torch.Tensor  # [H, W] 1 - T_final
    radii: torch.Tensor  # [N] int32 pixel radius (3 sigma), 0 for culled Gaussians
    n_touched: torch.Tensor  # [N] int32 pixels each Gaussian was composited into


def finish_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Expected depth of the visible surface: depth / alpha where alpha > DEPTH_EPS, else 0 (differentiable)."""
    ok = alpha > DEPTH_EPS
    return torch.where(ok, depth / torch.where(ok, alpha, torch.ones_like(alpha)), torch.zeros_like(depth))


def _empty(shape, dtype: torch.dtype, device) -> torch.Tensor:
    """Every buffer a kernel must fill completely comes from here (tests patch it to poison with NaN / -1)."""
    return torch.empty(shape, dtype=dtype, device=device)


class _ProjectFn(torch.autograd.Function):
    """EWA projection on the active backend: (means, quats, scales, opacities, colors, viewmat) -> proj [N, 10]
    rows in the PACKED layout (zeros for culled Gaussians), radius [N] and tile rect [N, 4] (not differentiable)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, viewmat, intr, width, height, near, far, impl, device):
        n, dev = means.shape[0], means.device
        proj = _empty((n, PACKED), torch.float32, dev)
        radius = _empty((n,), torch.int32, dev)
        rect = _empty((n, 4), torch.int32, dev)
        args = [t.detach().contiguous() for t in (means, quats, scales, opacities, colors, viewmat)]
        impl.project_forward(*args, intr, width, height, float(near), float(far), proj, radius, rect, device)
        ctx.save_for_backward(*args[:3], args[5], proj, radius)
        ctx.dims = (intr, width, height, impl, device)
        ctx.mark_non_differentiable(radius, rect)
        return proj, radius, rect

    @staticmethod
    def backward(ctx, g_proj, _g_radius, _g_rect):
        means, quats, scales, viewmat, proj, radius = ctx.saved_tensors
        intr, width, height, impl, device = ctx.dims
        n, dev = means.shape[0], means.device
        g_means = _empty((n, 3), torch.float32, dev)
        g_quats = _empty((n, 4), torch.float32, dev)
        g_scales = _empty((n, 3), torch.float32, dev)
        g_parts = _empty((n, 12), torch.float32, dev)  # per-Gaussian viewmat gradient: R row-major, then t
        g_proj = g_proj.contiguous()
        impl.project_backward(means, quats, scales, viewmat, intr, width, height, proj.detach(), radius, g_proj,
                              g_means, g_quats, g_scales, g_parts, device)
        g_view = torch.zeros(4, 4, dtype=torch.float32, device=dev)
        total = g_parts.sum(0)
        g_view[:3, :3] = total[:9].reshape(3, 3)
        g_view[:3, 3] = total[9:]
        return (g_means, g_quats, g_scales, g_proj[:, 5], g_proj[:, 6:9], g_view,
                None, None, None, None, None, None, None)


class _RasterFn(torch.autograd.Function):
    """packed [M, 10] depth-sorted attributes -> (color [H,W,3], depth [H,W], alpha [H,W]); hand-written backward."""

    @staticmethod
    def forward(ctx, packed, rect, background, width, height, impl, device):
        packed = packed.detach()  # the kernels see plain tensors; gradients come from backward()
        # Skip exp() where alpha cannot reach 1/255: power < -log(255 o) (minus a margin so that the exact
        # alpha test after exp, the one the twin applies, still makes every decision).
        pthr = (-torch.log(255.0 * packed[:, 5].detach()) - 1e-5).contiguous()
        ntx, nty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        n_entries = int(((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])).sum()) if rect.shape[0] else 0
        tile_start = _empty((ntx * nty + 1,), torch.int32, packed.device)
        entries = _empty((max(n_entries, 1),), torch.int32, packed.device)
        impl.bin_tiles(rect, ntx, nty, tile_start, entries, device)
        color = _empty((height, width, 3), torch.float32, packed.device)
        depth = _empty((height, width), torch.float32, packed.device)
        t_final = _empty((height, width), torch.float32, packed.device)
        last = _empty((height, width), torch.int32, packed.device)
        hits = _empty((max(n_entries, 1),), torch.int32, packed.device)
        impl.render_forward(packed, pthr, tile_start, entries, background, width, height, color, depth, t_final, last, hits,
                            device)
        ctx.save_for_backward(packed, pthr, tile_start, entries, background, t_final, last)
        ctx.dims = (width, height, n_entries, impl, device)
        ctx.mark_non_differentiable(hits)
        alpha = 1.0 - t_final
        return color, depth, alpha, hits[:n_entries], entries[:n_entries]

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha, _g_hits, _g_entries):
        packed, pthr, tile_start, entries, background, t_final, last = ctx.saved_tensors
        width, height, n_entries, impl, device = ctx.dims
        g_packed = torch.zeros_like(packed)
        if n_entries:
            g_color = g_color.contiguous() if g_color is not None else torch.zeros(height, width, 3, device=packed.device)
            g_depth = g_depth.contiguous() if g_depth is not None else torch.zeros(height, width, device=packed.device)
            g_alpha = g_alpha.contiguous() if g_alpha is not None else torch.zeros(height, width, device=packed.device)
            g_entry = _empty((n_entries, PACKED), torch.float32, packed.device)
            t_run = _empty((height, width), torch.float32, packed.device)  # per-pixel scratch of the reverse pass
            behind = _empty((height, width), torch.float32, packed.device)
            impl.render_backward(packed, pthr, tile_start, entries, background, width, height, t_final, last,
                                 g_color, g_depth, g_alpha, t_run, behind, g_entry, device)
            g_packed.index_add_(0, entries[:n_entries].long(), g_entry)
        g_bg = None
        if ctx.needs_input_grad[2] and g_color is not None:
            g_bg = (t_final[..., None] * g_color).sum((0, 1))  # colour = ... + T_final * background
        return g_packed, None, g_bg, None, None, None, None


def _check(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far, dev):
    """Shapes, dtypes and devices per argument; values (finite, opacity range, quaternion length) in one fused
    pass over the [N]-sized tensors — every small torch op costs thread wake-ups on a busy CPU — and per
    argument only on the error path, to name the culprit."""
    f32, f = (torch.float32,), (torch.float32, torch.float64)
    check_tensor("means", means, (None, 3), dtypes=f32, device=dev, finite=False)
    n = means.shape[0]
    per_gaussian = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
                    "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    for name, (x, shape) in per_gaussian.items():
        check_tensor(name, x, shape, dtypes=f32, device=dev, finite=False)
    check_tensor("viewmat", viewmat, (4, 4), dtypes=f, device=dev)
    check_tensor("K", K, (3, 3), dtypes=f, device=dev)
    if background is not None:
        check_tensor("background", background, (3,), dtypes=f, device=dev)
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise InputError(f"argument '{name}': expected a positive int, got {v!r}")
    if not (0.0 < float(near) < float(far)):
        raise InputError(f"arguments 'near', 'far': expected 0 < near < far, got near={near}, far={far}")
    if float(K[0, 0]) <= 0 or float(K[1, 1]) <= 0:
        raise InputError("argument 'K': focal lengths K[0,0], K[1,1] must be positive")
    if n == 0:
        return
    with torch.no_grad():
        table = torch.cat([means, quats, scales, opacities[:, None], colors], 1)  # [N, 14]
        qlen2 = (table[:, 3:7] * table[:, 3:7]).sum(-1)
        # sum(x * 0) is NaN exactly when some x is NaN or Inf; one reduction instead of one per argument
        ok = bool(torch.isfinite((table * 0).sum())) and bool((qlen2 >= 1e-20).all())
        ok = ok and bool(((opacities >= 0) & (opacities <= 1)).all())
    if ok:
        return
    for name, (x, shape) in per_gaussian.items():
        check_tensor(name, x, shape, dtypes=f32, device=dev)  # names the non-finite argument
    if not bool(((opacities >= 0) & (opacities <= 1)).all()):
        raise InputError("argument 'opacities': expected values in [0, 1]")
    raise InputError("argument 'quats': contains a zero-length quaternion")


def rasterize(
    means: torch.Tensor,  # [N, 3] float32, world frame (metres)
    quats: torch.Tensor,  # [N, 4] float32, wxyz, need not be normalised
    scales: torch.Tensor,  # [N, 3] float32, linear standard deviations (metres)
    opacities: torch.Tensor,  # [N] float32 in [0, 1]
    colors: torch.Tensor,  # [N, 3] float32
    viewmat: torch.Tensor,  # [4, 4] float32|float64, T_cam_world (world -> camera, OpenCV axes)
    K: torch.Tensor,  # [3, 3] float32|float64 intrinsics, pixel centres at integer coordinates
    width: int,
    height: int,
    *,
    background: torch.Tensor | None = None,  # [3], default black
    near: float = 0.01,  # metres
    far: float = 100.0,  # metres
) -> RenderOutput:
    """Render colour, depth and alpha of 3D Gaussians with the 3DGS rules on the active backend (`kernels.use`).

    Differentiable (torch autograd) with respect to means, quats, scales, opacities, colors, viewmat (and
    background). All tensors must live on the active backend's device. Returns `RenderOutput`; see
    `kernels/_ref_raster.py` for the exact rules.
    """
    b = active()
    _check(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far, b.torch_device)
    from . import backend_module

    impl = backend_module("raster")
    dev = means.device
    viewmat32 = viewmat.to(torch.float32)
    intr = tuple(float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    bg = torch.zeros(3, dtype=torch.float32, device=dev) if background is None else background.to(torch.float32)
    n = means.shape[0]
    proj, radius, rect = _ProjectFn.apply(means, quats, scales, opacities, colors, viewmat32, intr, int(width),
                                          int(height), near, far, backend_module("project"), b.device)
    idx = torch.nonzero(radius > 0).squeeze(1)
    order = idx[torch.sort(proj.detach()[idx, 9], stable=True).indices]  # front to back, ties by index
    packed = proj[order]
    color, depth, alpha, hits, entries = _RasterFn.apply(
        packed.contiguous(), rect[order].contiguous(), bg.contiguous(), int(width), int(height), impl, b.device)
    n_touched = torch.zeros(n, dtype=torch.int32, device=dev)
    if hits.numel():
        per_sorted = torch.zeros(order.shape[0], dtype=torch.int32, device=dev)
        per_sorted.index_add_(0, entries.long(), hits)
        n_touched[order] = per_sorted
    return RenderOutput(color=color, depth=depth, depth_normalised=finish_depth(depth, alpha), alpha=alpha,
                        radii=radius, n_touched=n_touched)


def twist_gradient(v_viewmat: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """dL/dxi [6] = [omega, v] at xi = 0 for viewmat = exp(xi) @ viewmat0, from dL/dviewmat [4, 4].

    With dT = hat(xi) T, dL = <G, hat(xi) T> = <G T^T, hat(xi)>: omega from the skew part of (G T^T)[:3, :3],
    v from its last column.
    """
    M = v_viewmat @ viewmat.T
    return torch.stack([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1], M[0, 3], M[1, 3], M[2, 3]])
