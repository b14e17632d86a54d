"""Warp implementation of the ICP kernels (see `kernels/icp.py` for the contract, `kernels/_ref_icp.py` for
the twins): normals from depth, neighbour moments, projective and nearest-neighbour association (wp.HashGrid).
The normal-equation reductions are in kernels/_warp/icp_reduce.py (one float64 row per block)."""

from __future__ import annotations

import torch
import warp as wp

from .launch import launch as _launch


# Forward-only kernels: no adjoint code to compile (ICP never differentiates through these).
wp.set_module_options({"enable_backward": False})


@wp.func
def _backproject(d: float, u: int, v: int, ifx: float, ify: float, cx: float, cy: float):
    # ifx, ify = 1 / fx, 1 / fy: multiplications instead of the divisions that dominated this kernel.
    return wp.vec3((float(u) - cx) * ifx * d, (float(v) - cy) * ify * d, d)


# GPU: (H, W) threads, one pixel each (chunk = 1), 256 per block; 54 registers (sm_86/87 cubins) -> 67 %
# occupancy; 5 depth reads per pixel, neighbours shared through L1; no scratch, no atomics.
@wp.kernel
def _vertices_normals(depth: wp.array2d(dtype=wp.float32), ifx: float, ify: float, cx: float, cy: float, jump: float,
                      chunk: int, v0: int, verts: wp.array2d(dtype=wp.vec3), normals: wp.array2d(dtype=wp.vec3)):
    # Thread (v, k) does pixels [k * chunk, (k + 1) * chunk) of row v: on the CPU a whole row (a thread per pixel
    # costs Warp's CPU loop an index division per pixel, as much as the pixel's own work), on CUDA one pixel.
    v, k = wp.tid()
    v = v + v0
    H = depth.shape[0]
    W = depth.shape[1]
    for u in range(k * chunk, wp.min(W, k * chunk + chunk)):
        d = depth[v, u]
        p = wp.vec3(0.0, 0.0, 0.0)
        if d > 0.0:
            p = _backproject(d, u, v, ifx, ify, cx, cy)
        verts[v, u] = p
        n = wp.vec3(0.0, 0.0, 0.0)
        if d > 0.0 and u > 0 and v > 0 and u < W - 1 and v < H - 1:
            dr = depth[v, u + 1]
            dl = depth[v, u - 1]
            dd = depth[v + 1, u]
            du = depth[v - 1, u]
            lim = jump * d
            ok = dr > 0.0 and dl > 0.0 and dd > 0.0 and du > 0.0
            ok = ok and wp.abs(dr - d) <= lim and wp.abs(dl - d) <= lim and wp.abs(dd - d) <= lim
            ok = ok and wp.abs(du - d) <= lim
            if ok:
                dx = _backproject(dr, u + 1, v, ifx, ify, cx, cy) - _backproject(dl, u - 1, v, ifx, ify, cx, cy)
                dy = _backproject(dd, u, v + 1, ifx, ify, cx, cy) - _backproject(du, u, v - 1, ifx, ify, cx, cy)
                c = wp.cross(dx, dy)
                ln = wp.length(c)
                if ln > 1.0e-12:
                    n = c * (1.0 / ln)
                    if wp.dot(n, p) > 0.0:
                        n = -n
        normals[v, u] = n


# GPU: one thread per query, 256 per block; 79 registers -> 50 % occupancy; float64 sums (1/64-rate on RTX 30xx
# and Orin, a few hundred per query: small next to the grid walk); no atomics. Grid scratch: see _Grid.
@wp.kernel
def _moments(grid: wp.uint64, points: wp.array(dtype=wp.vec3), queries: wp.array(dtype=wp.vec3), radius: float,
             i0: int, out: wp.array2d(dtype=wp.float64)):
    i = wp.tid() + i0
    q = queries[i]
    r2 = radius * radius
    n = wp.float64(0.0)
    s = wp.vec3d(0.0, 0.0, 0.0)
    sxx = wp.float64(0.0)
    sxy = wp.float64(0.0)
    sxz = wp.float64(0.0)
    syy = wp.float64(0.0)
    syz = wp.float64(0.0)
    szz = wp.float64(0.0)
    query = wp.hash_grid_query(grid, q, radius)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        p = points[j]
        if wp.length_sq(p - q) <= r2:
            x = wp.float64(p[0])
            y = wp.float64(p[1])
            z = wp.float64(p[2])
            n += wp.float64(1.0)
            s += wp.vec3d(x, y, z)
            sxx += x * x
            sxy += x * y
            sxz += x * z
            syy += y * y
            syz += y * z
            szz += z * z
    out[i, 0] = n
    out[i, 1] = s[0]
    out[i, 2] = s[1]
    out[i, 3] = s[2]
    out[i, 4] = sxx
    out[i, 5] = sxy
    out[i, 6] = sxz
    out[i, 7] = syy
    out[i, 8] = syz
    out[i, 9] = szz


@wp.func
def _xform(T: wp.mat44, p: wp.vec3):
    return wp.transform_point(T, p)


@wp.func
def _rotate(T: wp.mat44, p: wp.vec3):
    return wp.transform_vector(T, p)


@wp.func
def _project_assoc(p: wp.vec3, q: wp.vec3, sn_i: wp.vec3, T: wp.mat44,
                   tv: wp.array(dtype=wp.vec3), tn: wp.array(dtype=wp.vec3), H: int, W: int,
                   fx: float, fy: float, cx: float, cy: float, max_d: float, cos_min: float):
    # p: source point, q = T p. Returns the flat target pixel index or -1 (gates in kernels.icp).
    if p[2] <= 0.0 or q[2] <= 0.0:
        return -1
    iz = 1.0 / q[2]  # one division per point instead of two (the projection's largest cost)
    u = int(wp.floor(fx * q[0] * iz + cx + 0.5))
    v = int(wp.floor(fy * q[1] * iz + cy + 0.5))
    if u < 0 or v < 0 or u >= W or v >= H:
        return -1
    t = v * W + u
    n = tn[t]
    if n[0] == 0.0 and n[1] == 0.0 and n[2] == 0.0:
        return -1
    if wp.length_sq(q - tv[t]) > max_d * max_d:
        return -1
    if cos_min >= -1.0:
        if wp.dot(_rotate(T, sn_i), n) < cos_min:
            return -1
    return t


# GPU: one thread per source point, 256 per block; 22 registers -> full occupancy; one gather from the target
# maps; no scratch, no atomics.
@wp.kernel
def _assoc_projective(src: wp.array(dtype=wp.vec3), T: wp.mat44,
                      tv: wp.array(dtype=wp.vec3), tn: wp.array(dtype=wp.vec3), sn: wp.array(dtype=wp.vec3),
                      H: int, W: int, fx: float, fy: float, cx: float, cy: float, max_d: float, cos_min: float,
                      i0: int, out: wp.array(dtype=wp.int32)):
    i = wp.tid() + i0
    p = src[i]
    out[i] = _project_assoc(p, _xform(T, p), sn[i], T, tv, tn, H, W, fx, fy, cx, cy, max_d, cos_min)


# GPU: one thread per source point, 256 per block; 39 registers -> full occupancy; candidates of a cell are
# contiguous (points stored in cell order); no scratch, no atomics.
@wp.kernel
def _assoc_nearest(grid: wp.uint64, points: wp.array(dtype=wp.vec3), orig: wp.array(dtype=wp.int32),
                   src: wp.array(dtype=wp.vec3), T: wp.mat44, max_d: float, i0: int, out: wp.array(dtype=wp.int32)):
    # points are stored in grid order; orig maps them back, and ties go to the lowest original index.
    i = wp.tid() + i0
    q = _xform(T, src[i])
    best = max_d * max_d
    best_j = int(-1)
    query = wp.hash_grid_query(grid, q, max_d)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d2 = wp.length_sq(points[j] - q)
        if d2 <= best:
            oj = orig[j]
            if d2 < best or best_j < 0 or oj < best_j:
                best = d2
                best_j = oj
    out[i] = best_j


# GPU: one thread per point, 20 registers.
@wp.kernel
def _grid_order(grid: wp.uint64, out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = wp.hash_grid_point_id(grid, i)


def _mat(T: torch.Tensor) -> wp.mat44:
    """A [4, 4] pose as a kernel argument by value (kept in registers instead of re-read per point)."""
    return wp.mat44(*T.detach().cpu().reshape(-1).tolist())


def _sync(device: str) -> None:
    if device == "cuda":
        wp.synchronize_device(device)


def _arr(x: torch.Tensor, dtype=None):
    """A tensor as a kernel argument: Warp's bare array descriptor (no wp.array object per launch; the caller
    holds the tensor for the launch, which is synchronous on the CPU and synchronised on CUDA)."""
    return wp.from_torch(x, dtype=dtype, requires_grad=False, return_ctype=True)


def vertices_normals(depth: torch.Tensor, camera, jump: float, device: str):
    H, W = depth.shape
    verts = torch.empty(H, W, 3, dtype=torch.float32, device=depth.device)
    normals = torch.empty_like(verts)
    chunk = W if device == "cpu" else 1
    _launch(_vertices_normals, (H, W // chunk),
            [_arr(depth), 1.0 / camera.fx, 1.0 / camera.fy, camera.cx, camera.cy, jump, chunk, 0,
             _arr(verts, dtype=wp.vec3), _arr(normals, dtype=wp.vec3)], 7, device, work=H * W)
    _sync(device)
    return verts, normals


class _Grid:
    """GPU scratch: each wp.HashGrid(128, 128, 128) holds two int32 tables of 128^3 cells (16 MB), built twice here
    (radix sort on CUDA).

    wp.HashGrid over the points stored in the grid's own cell order (`order[k]` = original index of stored
    point k), so the candidates of a query are contiguous in memory: built once to learn the order, then again
    on the reordered points (measured 18 -> 14.5 ms CPU for 48k nearest-neighbour queries)."""

    def __init__(self, points: torch.Tensor, cell: float, device: str):
        first = wp.HashGrid(128, 128, 128, device=device)
        first.build(wp.from_torch(points, dtype=wp.vec3), cell)
        self.order = torch.empty(points.shape[0], dtype=torch.int32, device=points.device)
        if points.shape[0]:
            wp.launch(_grid_order, dim=points.shape[0], inputs=[first.id, _arr(self.order)], device=device)
            _sync(device)
        self.points = points[self.order.long()].contiguous()
        self.wp_points = wp.from_torch(self.points, dtype=wp.vec3)
        self.grid = wp.HashGrid(128, 128, 128, device=device)
        self.grid.build(self.wp_points, cell)


def build_grid(points: torch.Tensor, cell: float, device: str):
    return _Grid(points, cell, device)


def cloud_moments(grid: _Grid, points: torch.Tensor, queries: torch.Tensor, radius: float, device: str):
    out = torch.zeros(queries.shape[0], 10, dtype=torch.float64, device=queries.device)
    if queries.shape[0]:
        _launch(_moments, queries.shape[0],
                [grid.grid.id, grid.wp_points, _arr(queries, dtype=wp.vec3), radius, 0, _arr(out)],
                4, device)
        _sync(device)
    return out


def associate_projective(src, T, tv, tn, sn, camera, max_d: float, cos_min: float, device: str):
    out = torch.empty(src.shape[0], dtype=torch.int32, device=src.device)
    if src.shape[0]:
        H, W = tv.shape[:2]
        _launch(_assoc_projective, src.shape[0],
                [_arr(src, dtype=wp.vec3), _mat(T), _arr(tv.reshape(-1, 3), dtype=wp.vec3),
                 _arr(tn.reshape(-1, 3), dtype=wp.vec3), _arr(sn, dtype=wp.vec3), H, W,
                 camera.fx, camera.fy, camera.cx, camera.cy, max_d, cos_min, 0, _arr(out)], 13, device)
        _sync(device)
    return out


def associate_nearest(grid: _Grid, points, src, T, max_d: float, device: str):
    out = torch.empty(src.shape[0], dtype=torch.int32, device=src.device)
    if src.shape[0]:
        _launch(_assoc_nearest, src.shape[0],
                [grid.grid.id, grid.wp_points, _arr(grid.order), _arr(src, dtype=wp.vec3), _mat(T), max_d, 0,
                 _arr(out)], 6, device)
        _sync(device)
    return out


# The reduction (normal equations of point-to-plane and photometric residuals) lives in its own file; the backend
# module `icp` keeps exposing it.
from .icp_reduce import reduce_point_to_plane  # noqa: E402,F401  (imports this module's helpers)
