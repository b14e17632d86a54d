"""Differentiable 3D Gaussian splatting rasteriser (the 3DGS rules), colour + depth + alpha, Warp or Taichi.

One call is one autograd Function (`_RenderFn`) running five kernels on the active backend, with hand-written
backward kernels and no per-Gaussian torch operations in between:
1. projection (kernels/_<backend>/project.py, one thread per Gaussian): camera-space means, EWA 2D covariance
   with the 0.3 px low-pass, its inverse (conic), 3-sigma radius, the 16x16-tile rectangle, the number of tiles
   and the exp() skip threshold of every Gaussian; culls outside near/far, off-screen and degenerate ones and
   flags invalid input values (non-finite, zero quaternion, opacity outside [0, 1]);
2. binning (kernels/_<backend>/sort.py): per-tile lists of the visible Gaussians in depth order (ties by index),
   plus where every Gaussian's entries are. On the CPU a serial radix sort by depth and a counting sort by tile
   (Warp lists the tiles in one part per core); on the GPU devices the parallel steps of kernels/binning.py (tile
   counts, prefix sum, key scatter, one stable sort of (tile, depth) keys), the same lists bit for bit;
3. compositing (kernels/_<backend>/raster.py, one thread per tile): front to back over the tile's list, only
   the pixels of each Gaussian's alpha >= 1/255 ellipse; writes colour, depth, depth / alpha and alpha;
4. per-Gaussian hit counts (n_touched).
Backward: reverse compositing per tile writes each tile entry's gradient, then the projection backward sums a
Gaussian's entries and chains them to means, quats, scales, opacity, colour and the viewmat.

The rules are spelled out in `kernels/_ref_raster.py`, the dense twin this module is tested against.
The tracking gradient: parametrise `viewmat = kernels.se3.exp_torch(xi) @ viewmat0` (left perturbation in the
camera frame, xi = [omega, v]) and autograd turns the [4, 4] viewmat gradient into dL/dxi; `twist_gradient`
does the same contraction in closed form at xi = 0.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import torch

from .backend import active
from .checks import check_tensor
from .errors import InputError

TILE = 16  # pixels per tile side; the kernels hard-code the same value
PACKED = 10  # projected row: mean2d x, y, conic a, b, c, opacity, r, g, b, z
DEPTH_EPS = 1e-6  # alpha below which depth_normalised is 0
RADIX = 2048  # the binning's radix-sort histogram size (kernels/_<backend>/sort.py)


class RenderOutput(NamedTuple):
    color: torch.Tensor  # [H, W, 3] composited colour plus T_final * background
    depth: torch.Tensor  # [H, W] alpha-weighted depth sum_i z_i alpha_i T_i (metres, camera z)
    depth_normalised: torch.Tensor  # [H, W] depth / alpha where alpha > 1e-6, else 0
    alpha: torch.Tensor  # [H, W] 1 - T_final
    radii: torch.Tensor  # [N] int32 pixel radius (3 sigma), 0 for culled Gaussians
    n_touched: torch.Tensor | None  # [N] int32 pixels each Gaussian was composited into (None: not counted)


def finish_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Expected depth of the visible surface: depth / alpha where alpha > DEPTH_EPS, else 0 (differentiable)."""
    ok = alpha > DEPTH_EPS
    return torch.where(ok, depth / torch.where(ok, alpha, torch.ones_like(alpha)), torch.zeros_like(depth))


def _empty(shape, dtype: torch.dtype, device) -> torch.Tensor:
    """Every buffer a kernel must fill completely comes from here (tests patch it to poison with NaN / -1)."""
    return torch.empty(*shape, dtype=dtype, device=device)  # the sizes as arguments: ~0.5 us cheaper than a tuple


_I32, _F32 = torch.int32, torch.float32
_capacity: dict = {}  # (N, width, height) -> tile-entry buffer size that sufficed last time (grown on demand)


def _bin(sort, proj, ntiles, rect, n: int, ntx: int, nty: int, dev, device: str):
    """Depth-ordered per-tile lists (kernels/_<backend>/sort.py). Returns (n_entries, n_invalid, tile_start,
    entries, emit_start, emit_pos)."""
    nb = max(n, 1)
    status = _empty((3,), _I32, dev)
    emit_start = _empty((nb,), _I32, dev)
    scratch = torch.empty(5, max(nb, RADIX), dtype=_I32, device=dev)
    tile_start = _empty((ntx * nty + 1,), _I32, dev)
    cursor = torch.empty(ntx * nty, dtype=_I32, device=dev)
    key = (n, ntx, nty)
    cap = _capacity.get(key, 4 * n + ntx * nty)
    while True:
        entries = _empty((cap,), _I32, dev)
        emit_pos = _empty((cap,), _I32, dev)
        sort.bin_tiles(proj.view(_I32), ntiles, rect, n, ntx, ntx * nty, status, emit_start, scratch, tile_start,
                       cursor, entries, emit_pos, device)
        n_entries, n_bad, _n_visible = status.tolist()
        if n_bad or n_entries <= cap:
            break
        cap = n_entries + n_entries // 4 + 1
    if len(_capacity) > 256:  # N changes with every keyframe's seeding and pruning; keep the hints few
        _capacity.clear()
    _capacity[key] = cap
    return n_entries, n_bad, tile_start, entries, emit_start, emit_pos


class _RenderFn(torch.autograd.Function):
    """(means, quats, scales, opacities, colors, viewmat [4,4] f32, background [3]) -> (color [H,W,3], depth,
    depth_normalised, alpha [H,W], radii [N], n_touched [N]); hand-written backward to all seven inputs."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, viewmat, background, intr, width, height, near, far,
                impls, device, count_touched):
        project, sort, raster = impls
        n, dev = means.shape[0], means.device
        nb = max(n, 1)  # Taichi rejects 0-sized arguments
        proj = _empty((nb, PACKED), _F32, dev)
        radius = _empty((nb,), _I32, dev)
        rect = _empty((nb, 4), _I32, dev)
        ntiles = _empty((nb,), _I32, dev)
        pthr = _empty((nb,), _F32, dev)
        args = [t.detach().contiguous() for t in (means, quats, scales, opacities, colors, viewmat)]
        project.project_forward(*args, intr, width, height, float(near), float(far), proj, radius, rect, ntiles,
                                pthr, device)
        ntx, nty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        n_entries, n_bad, tile_start, entries, emit_start, emit_pos = _bin(sort, proj, ntiles, rect, n, ntx, nty,
                                                                           dev, device)
        if n_bad:
            _explain_invalid(means, quats, scales, opacities, colors)
        color = _empty((height, width, 3), _F32, dev)
        depth = _empty((height, width), _F32, dev)
        dnorm = _empty((height, width), _F32, dev)
        alpha = _empty((height, width), _F32, dev)
        t_final = _empty((height, width), _F32, dev)
        last = _empty((height, width), _I32, dev)
        hits = _empty((max(n_entries, 1),), _I32, dev)
        bg = background.detach().contiguous()
        raster.render_forward(proj, pthr, tile_start, entries, bg, width, height, color, depth, dnorm, alpha,
                              t_final, last, hits, device, count_hits=count_touched)
        n_touched = _empty((n if count_touched else 0,), _I32, dev)
        if count_touched:
            sort.count_touched(n, ntiles, emit_start, emit_pos, hits, n_touched, device)
        ctx.save_for_backward(*args[:3], args[5], proj, pthr, ntiles, tile_start, entries, emit_start, emit_pos, bg,
                              t_final, dnorm, last)
        ctx.dims = (intr, width, height, n_entries, impls, device)
        ctx.set_materialize_grads(False)  # an image without a gradient arrives as None, not as a zero image
        radii = radius if n == nb else radius[:n]
        ctx.mark_non_differentiable(radii, n_touched)
        return color, depth, dnorm, alpha, radii, n_touched

    @staticmethod
    def backward(ctx, g_color, g_depth, g_dnorm, g_alpha, _g_radii, _g_touched):
        (means, quats, scales, viewmat, proj, pthr, ntiles, tile_start, entries, emit_start, emit_pos, bg, t_final,
         dnorm, last) = ctx.saved_tensors
        # detached: the saved output comes back requiring grad, and Taichi, handed a tensor that requires grad,
        # allocates it a .grad (or warns, for a non-leaf) on every launch; the rest were saved detached
        dnorm = dnorm.detach()
        intr, width, height, n_entries, (project, _sort, raster), device = ctx.dims
        n, dev = means.shape[0], means.device
        g_bg = None
        if ctx.needs_input_grad[6]:
            g_bg = torch.zeros(3, dtype=_F32, device=dev) if g_color is None else \
                (t_final[..., None] * g_color).sum((0, 1))  # colour = ... + T_final * background
        if n == 0 or n_entries == 0:
            z = torch.zeros_like
            return (z(means), z(quats), z(scales), torch.zeros(n, dtype=_F32, device=dev), z(means),
                    torch.zeros(4, 4, dtype=_F32, device=dev), g_bg) + (None,) * 8
        img = (height, width)
        # image gradients may be strided (e.g. expanded from a sum); the backend makes them contiguous if it must
        zero = _black(dev)[0]  # a zero scalar, expanded to the images without a gradient
        g_color = zero.expand(*img, 3) if g_color is None else g_color
        g_depth, g_dnorm, g_alpha = (zero.expand(img) if g is None else g for g in (g_depth, g_dnorm, g_alpha))
        g_entry = _empty((n_entries, PACKED), _F32, dev)
        raster.render_backward(proj, pthr, tile_start, entries, bg, width, height, t_final, dnorm, last, g_color,
                               g_depth, g_dnorm, g_alpha, g_entry, device)
        g_means = _empty((n, 3), _F32, dev)
        g_quats = _empty((n, 4), _F32, dev)
        g_scales = _empty((n, 3), _F32, dev)
        g_opac = _empty((n,), _F32, dev)
        g_colors = _empty((n, 3), _F32, dev)
        g_parts = _empty((n, 12), _F32, dev)  # per-Gaussian viewmat gradient: R row-major, then t
        g_view = _empty((4, 4), _F32, dev) if ctx.needs_input_grad[5] else None  # None: parts not summed
        project.project_backward(means, quats, scales, viewmat, intr, width, height, proj, ntiles, emit_start,
                                 emit_pos, g_entry, g_means, g_quats, g_scales, g_opac, g_colors, g_parts, g_view,
                                 device)
        return (g_means, g_quats, g_scales, g_opac, g_colors, g_view, g_bg) + (None,) * 8


def _explain_invalid(means, quats, scales, opacities, colors) -> None:
    """The projection flagged invalid values: name the argument (slow path, only on error)."""
    n = means.shape[0]
    for name, x, shape in (("means", means, (n, 3)), ("quats", quats, (n, 4)), ("scales", scales, (n, 3)),
                           ("opacities", opacities, (n,)), ("colors", colors, (n, 3))):
        check_tensor(name, x, shape, dtypes=(_F32,), device=x.device)  # names the non-finite argument
    if not bool(((opacities >= 0) & (opacities <= 1)).all()):
        raise InputError("argument 'opacities': expected values in [0, 1]")
    raise InputError("argument 'quats': contains a zero-length quaternion")


def _plain(means, quats, scales, opacities, colors, viewmat, K, background, dev: str) -> bool:
    """The common case, cheaply (~10 us less than check_tensor's per-argument checks): float32 tensors of the
    expected shapes on `dev` ("cpu" | "cuda"), a finite background. False: let check_tensor look (and name what is
    wrong, if anything)."""
    on = "is_cuda" if dev == "cuda" else "is_cpu"
    ts = (means, quats, scales, opacities, colors, viewmat, K) + (() if background is None else (background,))
    if not all(isinstance(x, torch.Tensor) and getattr(x, on) for x in ts):
        return False
    n = means.shape[0]
    shapes = ((n, 3), (n, 4), (n, 3), (n,), (n, 3))
    if any(x.dtype is not _F32 or x.shape != sh for x, sh in zip(ts, shapes)):
        return False
    f = (torch.float32, torch.float64)
    if viewmat.shape != (4, 4) or K.shape != (3, 3) or viewmat.dtype not in f or K.dtype not in f:
        return False
    return background is None or (background.shape == (3,) and background.dtype in f
                                  and all(math.isfinite(v) for v in background.tolist()))


def _check(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near, far, dev):
    """Shapes, dtypes and devices per argument, the camera's values here; the per-Gaussian values (finite, opacity
    range, quaternion length) are checked by the projection kernel, which flags them for `_explain_invalid`.
    Returns (viewmat as float32, intrinsics (fx, fy, cx, cy))."""
    if not _plain(means, quats, scales, opacities, colors, viewmat, K, background, dev):
        f32, f = (_F32,), (torch.float32, torch.float64)
        check_tensor("means", means, (None, 3), dtypes=f32, device=dev, finite=False)
        n = means.shape[0]
        per_gaussian = {"quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
                        "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
        for name, (x, shape) in per_gaussian.items():
            check_tensor(name, x, shape, dtypes=f32, device=dev, finite=False)
        check_tensor("viewmat", viewmat, (4, 4), dtypes=f, device=dev, finite=False)
        check_tensor("K", K, (3, 3), dtypes=f, device=dev, finite=False)
        if background is not None:
            check_tensor("background", background, (3,), dtypes=f, device=dev)
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise InputError(f"argument '{name}': expected a positive int, got {v!r}")
    if not (0.0 < float(near) < float(far)):
        raise InputError(f"arguments 'near', 'far': expected 0 < near < far, got near={near}, far={far}")
    viewmat32 = viewmat.to(_F32)
    k = K.tolist()  # nested lists (tolist is ~1.5 us cheaper per matrix than flattening a tensor first)
    for name, rows in (("viewmat", viewmat32.tolist()), ("K", k)):
        if not all(map(math.isfinite, itertools.chain(*rows))):
            raise InputError(f"argument '{name}': contains NaN or Inf")
    if k[0][0] <= 0 or k[1][1] <= 0:
        raise InputError("argument 'K': focal lengths K[0,0], K[1,1] must be positive")
    return viewmat32, (k[0][0], k[1][1], k[0][2], k[1][2])


_IMPLS: dict = {}
_BLACK: dict = {}  # device -> the default background, zeros [3] (read only, never handed out)


def _black(dev) -> torch.Tensor:
    b = _BLACK.get(dev)
    if b is None:
        b = _BLACK[dev] = torch.zeros(3, dtype=_F32, device=dev)
    return b


def _impls(b):
    """(project, sort, raster) modules of the active backend, cached."""
    if b.name not in _IMPLS:
        from . import backend_module

        _IMPLS[b.name] = tuple(backend_module(m) for m in ("project", "sort", "raster"))
    return _IMPLS[b.name]


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
    count_touched: bool = True,  # False: n_touched is None (saves a pass over the tile entries)
) -> RenderOutput:
    """Render colour, depth and alpha of 3D Gaussians with the 3DGS rules on the active backend (`kernels.use`).

    Differentiable (torch autograd) with respect to means, quats, scales, opacities, colors, viewmat (and
    background). All tensors must live on the active backend's device. Returns `RenderOutput`; see
    `kernels/_ref_raster.py` for the exact rules.
    """
    b = active()
    viewmat32, intr = _check(means, quats, scales, opacities, colors, viewmat, K, width, height, background, near,
                             far, b.torch_device)
    dev = means.device
    bg = _black(dev) if background is None else background.to(_F32)
    color, depth, dnorm, alpha, radii, n_touched = _RenderFn.apply(
        means, quats, scales, opacities, colors, viewmat32, bg, intr, int(width), int(height), near, far, _impls(b),
        b.device, bool(count_touched))
    return RenderOutput(color=color, depth=depth, depth_normalised=dnorm, alpha=alpha, radii=radii,
                        n_touched=n_touched if count_touched else None)


def twist_gradient(v_viewmat: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """dL/dxi [6] = [omega, v] at xi = 0 for viewmat = exp(xi) @ viewmat0, from dL/dviewmat [4, 4].

    With dT = hat(xi) T, dL = <G, hat(xi) T> = <G T^T, hat(xi)>: omega from the skew part of (G T^T)[:3, :3],
    v from its last column.
    """
    M = v_viewmat @ viewmat.T
    return torch.stack([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1], M[0, 3], M[1, 3], M[2, 3]])
