"""Differentiable 3D Gaussian splatting rasteriser (the 3DGS rules), colour + depth + alpha, Warp or Taichi.

Pipeline, one call:
1. `_project` (torch, float32, autograd): camera-space means, EWA 2D covariance with the 0.3 px low-pass, its
   inverse (conic), 3-sigma radius and the 16x16-tile rectangle of every Gaussian; culls behind near/far,
   off-screen and degenerate ones. O(N) elementwise work; autograd carries its gradients to means, quats,
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


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:  # [N, 4] wxyz -> [N, 3, 3]
    q = q * torch.rsqrt((q * q).sum(-1, keepdim=True))
    w, x, y, z = q.unbind(-1)
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    return torch.stack(
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
         2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
         2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], -1).reshape(-1, 3, 3)


def _project(means, quats, scales, viewmat, K, width: int, height: int, near: float, far: float):
    """EWA projection, float32. Returns mean2d [N,2], conic [N,3] (a, b, c of the inverse 2D covariance),
    z [N], radius [N] int32, rect [N,4] int32 tile range (x0, y0, x1, y1; ends exclusive), visible [N] bool."""
    R_v, t_v = viewmat[:3, :3], viewmat[:3, 3]
    p = torch.addmm(t_v, means, R_v.T)  # [N, 3] camera frame
    x, y, z = p.unbind(-1)
    valid = (z >= near) & (z <= far)
    zs = torch.where(valid, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # 3DGS clamps the Jacobian's x/z, y/z to 1.3x the field of view so off-axis giants stay bounded.
    lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    inv_z = 1.0 / zs
    u = torch.minimum(torch.maximum(x * inv_z, -(cx / fx + lim_x)), (width - cx) / fx + lim_x)
    v = torch.minimum(torch.maximum(y * inv_z, -(cy / fy + lim_y)), (height - cy) / fy + lim_y)
    # T = J R_v R(q) S: rows of the 2x3 map from the Gaussian's unit frame to pixels.
    Mc = torch.matmul(R_v, _quat_to_rotmat(quats)) * scales[:, None, :]  # [N, 3, 3]
    T0 = (fx * inv_z)[:, None] * (Mc[:, 0] - u[:, None] * Mc[:, 2])  # [N, 3]
    T1 = (fy * inv_z)[:, None] * (Mc[:, 1] - v[:, None] * Mc[:, 2])
    a = (T0 * T0).sum(-1) + 0.3
    b = (T0 * T1).sum(-1)
    c = (T1 * T1).sum(-1) + 0.3
    det = a * c - b * b
    visible = valid & (det > 0)
    inv_det = 1.0 / torch.where(visible, det, torch.ones_like(det))
    conic = torch.stack([c * inv_det, -b * inv_det, a * inv_det], -1)
    mean2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))))
        ntx, nty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        m = mean2d.detach()
        x0 = torch.floor((m[:, 0] - radius) / TILE).clamp(0, ntx)
        x1 = (torch.floor((m[:, 0] + radius) / TILE) + 1).clamp(0, ntx)
        y0 = torch.floor((m[:, 1] - radius) / TILE).clamp(0, nty)
        y1 = (torch.floor((m[:, 1] + radius) / TILE) + 1).clamp(0, nty)
        visible = visible & (x1 > x0) & (y1 > y0)
        rect = torch.stack([x0, y0, x1, y1], -1).to(torch.int32)
        radius = torch.where(visible, radius.clamp(max=2**30), torch.zeros_like(radius)).to(torch.int32)
    return mean2d, conic, z, radius, rect, visible


class _RasterFn(torch.autograd.Function):
    """packed [M, 10] depth-sorted attributes -> (color [H,W,3], depth [H,W], alpha [H,W]); hand-written backward."""

    @staticmethod
    def forward(ctx, packed, rect, background, width, height, impl, device):
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
        return g_packed, None, None, None, None, None, None


def _check(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far, dev):
    f32, f = (torch.float32,), (torch.float32, torch.float64)
    check_tensor("means", means, (None, 3), dtypes=f32, device=dev)
    n = means.shape[0]
    check_tensor("quats", quats, (n, 4), dtypes=f32, device=dev)
    check_tensor("scales", scales, (n, 3), dtypes=f32, device=dev)
    check_tensor("opacities", opacities, (n,), dtypes=f32, device=dev)
    check_tensor("colors", colors, (n, 3), dtypes=f32, device=dev)
    check_tensor("viewmat", viewmat, (4, 4), dtypes=f, device=dev)
    check_tensor("K", K, (3, 3), dtypes=f, device=dev)
    if background is not None:
        check_tensor("background", background, (3,), dtypes=f, device=dev)
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise InputError(f"argument '{name}': expected a positive int, got {v!r}")
    if not (0.0 < float(near) < float(far)):
        raise InputError(f"arguments 'near', 'far': expected 0 < near < far, got near={near}, far={far}")
    if n and bool(((opacities < 0) | (opacities > 1)).any()):
        raise InputError("argument 'opacities': expected values in [0, 1]")
    if n and bool(((quats * quats).sum(-1) < 1e-20).any()):
        raise InputError("argument 'quats': contains a zero-length quaternion")
    if float(K[0, 0]) <= 0 or float(K[1, 1]) <= 0:
        raise InputError("argument 'K': focal lengths K[0,0], K[1,1] must be positive")


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
    viewmat32, K32 = viewmat.to(torch.float32), K.to(torch.float32)
    bg = torch.zeros(3, dtype=torch.float32, device=dev) if background is None else background.to(torch.float32)
    n = means.shape[0]
    mean2d, conic, z, radius, rect, visible = _project(means, quats, scales, viewmat32, K32, width, height, near, far)
    idx = torch.nonzero(visible).squeeze(1)
    order = idx[torch.sort(z.detach()[idx], stable=True).indices]  # front to back, ties by index
    packed = torch.cat([mean2d[order], conic[order], opacities[order, None], colors[order], z[order, None]], 1)
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
