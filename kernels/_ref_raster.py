"""The rasteriser's twin: an obvious, dense, pure-torch 3D Gaussian splatting renderer (the specification).

Every pixel is evaluated against every Gaussian ([P, N] tensors), in the dtype of the inputs (pass float64 for
finite differences); gradients come from torch autograd. It implements exactly the rules of the production
rasteriser in `kernels.raster` (the 3DGS rules):

- camera-space mean p = R_v mu + t_v (viewmat is world-to-camera, OpenCV axes); culled when z < near or z > far;
- EWA projection: cov2d = J (R_v Sigma R_v^T) J^T + 0.3 I, J the perspective Jacobian with x/z, y/z clamped to
  1.3x the field of view (as 3DGS/gsplat do, so huge off-axis Gaussians stay finite); Sigma = R(q) S S R(q)^T;
- radius = ceil(3 sqrt(lambda_max(cov2d))) px; the Gaussian touches the 16x16 tiles whose index range is
  floor((mean2d -/+ radius) / 16); culled when that range is empty;
- pixel centres sit at integer coordinates (kernels.camera convention);
- a Gaussian is evaluated at every pixel of every tile it touches (not only inside its radius); the kernels list
  only the touched tiles that meet the box of its alpha >= 1/255 ellipse (widened by 1 %), which changes no
  pixel: the others fail the alpha test;
- per pixel, Gaussians are taken front to back by camera z (ties broken by index):
  alpha = min(0.99, o exp(power)), skipped when power > 0 or alpha < 1/255, and compositing stops before the
  Gaussian that would bring the transmittance below 1e-4;
- color = sum c_i alpha_i T_i + T_final background, depth = sum z_i alpha_i T_i, alpha = 1 - T_final.
"""

from __future__ import annotations

import math

import torch

from .raster import TILE, RenderOutput, finish_depth

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOW_PASS = 0.3


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] wxyz (any length) -> [N, 3, 3]."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def project_reference(means, quats, scales, viewmat, K, width, height, near, far):
    """Dense EWA projection. Returns (mean2d [N,2], conic [N,2,2], z [N], radius [N] float, tile rect [N,4]
    (x0, y0, x1, y1) exclusive ends, visible [N] bool)."""
    R_v, t_v = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R_v.T + t_v
    x, y, z = p.unbind(-1)
    valid_z = (z >= near) & (z <= far)
    zs = torch.where(valid_z, z, torch.ones_like(z))  # culled ones get a harmless depth
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u = torch.minimum(torch.maximum(x / zs, -(cx / fx + 0.3 * tan_x)), (width - cx) / fx + 0.3 * tan_x)
    v = torch.minimum(torch.maximum(y / zs, -(cy / fy + 0.3 * tan_y)), (height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * u / zs, zero, fy / zs, -fy * v / zs], -1).reshape(-1, 2, 3)
    M = _quat_to_rotmat(quats) * scales[:, None, :]
    Sigma_cam = R_v @ (M @ M.transpose(1, 2)) @ R_v.T
    eye2 = torch.eye(2, dtype=means.dtype, device=means.device)
    cov2d = J @ Sigma_cam @ J.transpose(1, 2) + LOW_PASS * eye2
    det = torch.linalg.det(cov2d)
    visible = valid_z & (det > 0)
    conic = torch.linalg.inv(torch.where(visible[:, None, None], cov2d, eye2))
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():
        a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        tx = (width + TILE - 1) // TILE
        ty = (height + TILE - 1) // TILE
        m = mean2d.detach()
        x0 = torch.floor((m[:, 0] - radius) / TILE).clamp(0, tx)
        x1 = (torch.floor((m[:, 0] + radius) / TILE) + 1).clamp(0, tx)
        y0 = torch.floor((m[:, 1] - radius) / TILE).clamp(0, ty)
        y1 = (torch.floor((m[:, 1] + radius) / TILE) + 1).clamp(0, ty)
        visible = visible & (x1 > x0) & (y1 > y0)
        rect = torch.stack([x0, y0, x1, y1], -1)
    return mean2d, conic, z, radius, rect, visible


def rasterize_reference(
    means: torch.Tensor,  # [N, 3] world frame
    quats: torch.Tensor,  # [N, 4] wxyz, need not be normalised
    scales: torch.Tensor,  # [N, 3] linear (metres)
    opacities: torch.Tensor,  # [N] in (0, 1)
    colors: torch.Tensor,  # [N, 3]
    viewmat: torch.Tensor,  # [4, 4] T_cam_world
    K: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    background: torch.Tensor | None = None,  # [3]
    near: float = 0.01,
    far: float = 100.0,
    window: tuple[int, int, int, int] | None = None,  # (x0, y0, x1, y1): only these pixels, end exclusive
) -> RenderOutput:
    """Dense twin of `kernels.rasterize` (same signature and outputs), differentiable by autograd.

    Works in the dtype of `means` (every input is cast to it); memory is O(H W N), so keep scenes small.
    window: evaluate only the pixels [y0, y1) x [x0, x1) of the width x height image (images [y1-y0, x1-x0],
    n_touched counting those pixels): a few tiles of a working-size image with the full image's projection.
    """
    dt, dev = means.dtype, means.device
    quats, scales, opacities, colors, viewmat, K = (t.to(dt) for t in (quats, scales, opacities, colors, viewmat, K))
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else background.to(dt)
    n = means.shape[0]
    mean2d, conic, z, radius, rect, visible = project_reference(means, quats, scales, viewmat, K, width, height, near, far)

    x0, y0, x1, y1 = window if window is not None else (0, 0, width, height)
    ys, xs = torch.meshgrid(torch.arange(y0, y1, device=dev), torch.arange(x0, x1, device=dev), indexing="ij")
    px, py = xs.reshape(-1).to(dt), ys.reshape(-1).to(dt)  # [P]
    tile_x, tile_y = (xs.reshape(-1) // TILE).to(dt), (ys.reshape(-1) // TILE).to(dt)
    in_rect = (
        (tile_x[:, None] >= rect[None, :, 0]) & (tile_x[:, None] < rect[None, :, 2])
        & (tile_y[:, None] >= rect[None, :, 1]) & (tile_y[:, None] < rect[None, :, 3])
    )  # [P, N]
    dx = px[:, None] - mean2d[None, :, 0]
    dy = py[:, None] - mean2d[None, :, 1]
    A, B, C = conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]
    power = -0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy
    alpha = torch.clamp(opacities * torch.exp(torch.clamp(power, max=0.0)), max=ALPHA_MAX)
    keep = visible[None, :] & in_rect & (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))

    # Front to back by depth, ties by index (a stable sort); culled Gaussians have alpha 0 everywhere.
    order = torch.sort(torch.where(visible, z, torch.full_like(z, math.inf)).detach(), stable=True).indices
    alpha = alpha[:, order]
    with torch.no_grad():
        live = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN  # stop before the one crossing T_MIN
    alpha = alpha * live
    one_minus = 1.0 - alpha
    T_incl = torch.cumprod(one_minus, dim=1)
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    w = alpha * T_excl  # [P, N]
    T_final = T_incl[:, -1] if n else torch.ones(px.shape[0], dtype=dt, device=dev)
    color = w @ colors[order] + T_final[:, None] * bg
    depth = w @ torch.where(visible, z, torch.zeros_like(z))[order]
    alpha_img = 1.0 - T_final

    n_touched = torch.zeros(n, dtype=torch.int32, device=dev)
    n_touched[order] = (alpha.detach() > 0).sum(0).to(torch.int32)
    radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    depth = depth.reshape(y1 - y0, x1 - x0)
    alpha_img = alpha_img.reshape(y1 - y0, x1 - x0)
    return RenderOutput(
        color=color.reshape(y1 - y0, x1 - x0, 3), depth=depth, depth_normalised=finish_depth(depth, alpha_img),
        alpha=alpha_img, radii=radii, n_touched=n_touched,
    )
