"""Taichi implementation of the ICP kernels (contract in `kernels/icp.py`, twins in `kernels/_ref_icp.py`).

Neighbour search uses a uniform grid of cubic cells hashed into a power-of-two table; the table is built with
torch (counting sort of points by cell hash) and queried here. Points keep their own cell coordinates so hash
collisions between cells never mix neighbour sets. Reductions write one float64 row per block; Taichi runs the
outermost loop over blocks in parallel on every core (on the CPU spread over SPREAD iterations each: Taichi makes
CPU tasks of >= 512 iterations, so 64 blocks or 480 rows were one task on one core).
"""


import math

import taichi as ti
import torch

from ..icp import N_SLOTS, n_blocks, reduce_terms
from .launch import SPREAD, on_cpu

_P1, _P2, _P3 = 73856093, 19349663, 83492791

f32_2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
f32_3 = ti.types.ndarray(dtype=ti.f32, ndim=3)


@ti.func
def _xform(T: ti.template(), x, y, z):
    return ti.Vector([T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3],
                      T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3],
                      T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]])


@ti.func
def _bp(d, u, v, ifx, ify, cx, cy):
    # ifx, ify = 1 / fx, 1 / fy: multiplications instead of divisions (same arithmetic as the Warp kernel).
    return ti.Vector([(ti.cast(u, ti.f32) - cx) * ifx * d, (ti.cast(v, ti.f32) - cy) * ify * d, d])


# GPU (CUDA / Vulkan): one pixel per thread (chunk = 1), Taichi's default 128 per block / workgroup,
# grid-stride; no scratch, no atomics.
@ti.kernel
def _vertices_normals(depth: f32_2, ifx: ti.f32, ify: ti.f32, cx: ti.f32, cy: ti.f32, jump: ti.f32, chunk: ti.i32,
                      verts: f32_3, normals: f32_3):
    H, W = depth.shape[0], depth.shape[1]
    # Parallel over (row, chunk of `chunk` pixels): whole rows on the CPU (no index division per pixel), one
    # pixel per thread on CUDA.
    nk = (W + chunk - 1) // chunk
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: rows spread over the cores (kernels/_taichi/launch.py)
    for it in range(H * nk * sp):
        if it % sp != 0:
            continue
        v = it // sp // nk
        kc = it // sp - v * nk
        for u in range(kc * chunk, ti.min(W, kc * chunk + chunk)):
            d = depth[v, u]
            p = ti.Vector([0.0, 0.0, 0.0])
            if d > 0.0:
                p = _bp(d, u, v, ifx, ify, cx, cy)
            n = ti.Vector([0.0, 0.0, 0.0])
            if d > 0.0 and u > 0 and v > 0 and u < W - 1 and v < H - 1:
                dr, dl, dd, du = depth[v, u + 1], depth[v, u - 1], depth[v + 1, u], depth[v - 1, u]
                lim = jump * d
                ok = dr > 0.0 and dl > 0.0 and dd > 0.0 and du > 0.0
                ok = ok and ti.abs(dr - d) <= lim and ti.abs(dl - d) <= lim and ti.abs(dd - d) <= lim and ti.abs(du - d) <= lim
                if ok:
                    dx = _bp(dr, u + 1, v, ifx, ify, cx, cy) - _bp(dl, u - 1, v, ifx, ify, cx, cy)
                    dy = _bp(dd, u, v + 1, ifx, ify, cx, cy) - _bp(du, u, v - 1, ifx, ify, cx, cy)
                    c = dx.cross(dy)
                    ln = c.norm()
                    if ln > 1.0e-12:
                        n = c * (1.0 / ln)
                        if n.dot(p) > 0.0:
                            n = -n
            for k in ti.static(range(3)):
                verts[v, u, k] = p[k]
                normals[v, u, k] = n[k]


@ti.func
def _hash(cx, cy, cz, mask):
    return ((ti.cast(cx, ti.i64) * _P1) ^ (ti.cast(cy, ti.i64) * _P2) ^ (ti.cast(cz, ti.i64) * _P3)) & mask


# GPU: one query per thread, 128 per block / workgroup; float64 sums (Vulkan needs shaderFloat64) and int64
# cell hashes (shaderInt64); no atomics.
@ti.kernel
def _moments(spts: f32_2, scell: ti.types.ndarray(dtype=ti.i32, ndim=2), start: ti.types.ndarray(dtype=ti.i32, ndim=1),
             cnt: ti.types.ndarray(dtype=ti.i32, ndim=1), h: ti.f32, mask: ti.i64, reach: ti.i32,
             queries: f32_2, radius: ti.f32, out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    for i in range(queries.shape[0]):
        q = ti.Vector([queries[i, 0], queries[i, 1], queries[i, 2]])
        c0 = ti.floor(q / h, ti.i32)
        r2 = radius * radius
        acc = ti.Vector.zero(ti.f64, 10)
        # Three nested loops, not ti.ndrange: its run-time bounds cost two integer divisions per cell.
        for dx in range(-reach, reach + 1):
            for dy in range(-reach, reach + 1):
                for dz in range(-reach, reach + 1):
                    cx, cy, cz = c0[0] + dx, c0[1] + dy, c0[2] + dz
                    hb = _hash(cx, cy, cz, mask)
                    for k in range(start[hb], start[hb] + cnt[hb]):
                        if scell[k, 0] == cx and scell[k, 1] == cy and scell[k, 2] == cz:
                            p = ti.Vector([spts[k, 0], spts[k, 1], spts[k, 2]])
                            if (p - q).norm_sqr() <= r2:
                                x, y, z = ti.cast(p[0], ti.f64), ti.cast(p[1], ti.f64), ti.cast(p[2], ti.f64)
                                acc += ti.Vector([1.0, x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], dt=ti.f64)
        for k in ti.static(range(10)):
            out[i, k] = acc[k]


# GPU: one source point per thread, 128 per block / workgroup; int64 hashes (Vulkan: shaderInt64); no atomics.
@ti.kernel
def _assoc_nearest(spts: f32_2, scell: ti.types.ndarray(dtype=ti.i32, ndim=2), sidx: ti.types.ndarray(dtype=ti.i32, ndim=1),
                   start: ti.types.ndarray(dtype=ti.i32, ndim=1), cnt: ti.types.ndarray(dtype=ti.i32, ndim=1),
                   h: ti.f32, mask: ti.i64, reach: ti.i32, src: f32_2, T: f32_2, max_d: ti.f32,
                   out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    for i in range(src.shape[0]):
        q = _xform(T, src[i, 0], src[i, 1], src[i, 2])
        c0 = ti.floor(q / h, ti.i32)
        best = max_d * max_d
        best_j = -1
        # Three nested loops, not ti.ndrange: its run-time bounds cost two integer divisions per cell.
        for dx in range(-reach, reach + 1):
            for dy in range(-reach, reach + 1):
                for dz in range(-reach, reach + 1):
                    cx, cy, cz = c0[0] + dx, c0[1] + dy, c0[2] + dz
                    hb = _hash(cx, cy, cz, mask)
                    for k in range(start[hb], start[hb] + cnt[hb]):
                        if scell[k, 0] == cx and scell[k, 1] == cy and scell[k, 2] == cz:
                            d2 = (ti.Vector([spts[k, 0], spts[k, 1], spts[k, 2]]) - q).norm_sqr()
                            j = sidx[k]
                            if d2 < best or (d2 == best and (best_j < 0 or j < best_j)):
                                best = d2
                                best_j = j
        out[i] = best_j


@ti.func
def _project_assoc(p, q, T: ti.template(), tv: ti.template(), tn: ti.template(), sn: ti.template(), i, H, W,
                   fx, fy, cx, cy, max_d, cos_min):
    # p: source point, q = T p; flat target index or -1 (gates in kernels.icp).
    res = -1
    if p[2] > 0.0 and q[2] > 0.0:
        iz = 1.0 / q[2]  # one division per point instead of two (same arithmetic as the Warp kernel)
        u = ti.cast(ti.floor(fx * q[0] * iz + cx + 0.5), ti.i32)
        v = ti.cast(ti.floor(fy * q[1] * iz + cy + 0.5), ti.i32)
        if u >= 0 and v >= 0 and u < W and v < H:
            t = v * W + u
            n = ti.Vector([tn[t, 0], tn[t, 1], tn[t, 2]])
            ok = not (n[0] == 0.0 and n[1] == 0.0 and n[2] == 0.0)
            ok = ok and (q - ti.Vector([tv[t, 0], tv[t, 1], tv[t, 2]])).norm_sqr() <= max_d * max_d
            if ok and cos_min >= -1.0:
                rn = _xform(T, sn[i, 0], sn[i, 1], sn[i, 2]) - ti.Vector([T[0, 3], T[1, 3], T[2, 3]])
                ok = rn.dot(n) >= cos_min
            if ok:
                res = t
    return res


# GPU: one source point per thread, 128 per block / workgroup; no scratch, no atomics.
@ti.kernel
def _assoc_projective(src: f32_2, T: f32_2, tv: f32_2, tn: f32_2, sn: f32_2, H: ti.i32, W: ti.i32, fx: ti.f32,
                      fy: ti.f32, cx: ti.f32, cy: ti.f32, max_d: ti.f32, cos_min: ti.f32,
                      out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    for i in range(src.shape[0]):
        p = ti.Vector([src[i, 0], src[i, 1], src[i, 2]])
        out[i] = _project_assoc(p, _xform(T, p[0], p[1], p[2]), T, tv, tn, sn, i, H, W, fx, fy, cx, cy, max_d, cos_min)


@ti.func
def _bilinear1(img: ti.template(), u, v):
    x0 = ti.cast(ti.floor(u), ti.i32)
    y0 = ti.cast(ti.floor(v), ti.i32)
    a = u - ti.cast(x0, ti.f32)
    b = v - ti.cast(y0, ti.f32)
    return (img[y0, x0] * (1.0 - a) * (1.0 - b) + img[y0, x0 + 1] * a * (1.0 - b)
            + img[y0 + 1, x0] * (1.0 - a) * b + img[y0 + 1, x0 + 1] * a * b)


@ti.func
def _robust_w(r, kind, k):
    a = ti.abs(r)
    w = 1.0
    if kind == 1:
        if a > k:
            w = k / a
    elif kind == 2:
        w = 0.0
        if a <= k:
            t = 1.0 - (r / k) * (r / k)
            w = t * t
    return w


SUB = 64  # points summed in float32 before each float64 flush


@ti.func
def _contrib(J, w, r, e0, e1, e2, e3, e4, e5):
    # Packed per-point terms: [0:21] upper triangle of w J J^T (row-major), [21:27] w r J, [27:33] the extras.
    b = w * J
    return ti.Vector([b[0] * J[0], b[0] * J[1], b[0] * J[2], b[0] * J[3], b[0] * J[4], b[0] * J[5],
                      b[1] * J[1], b[1] * J[2], b[1] * J[3], b[1] * J[4], b[1] * J[5],
                      b[2] * J[2], b[2] * J[3], b[2] * J[4], b[2] * J[5],
                      b[3] * J[3], b[3] * J[4], b[3] * J[5], b[4] * J[4], b[4] * J[5], b[5] * J[5],
                      b[0] * r, b[1] * r, b[2] * r, b[3] * r, b[4] * r, b[5] * r, e0, e1, e2, e3, e4, e5], dt=ti.f32)


# GPU: one thread per block of points (n_blocks: up to 16384, grid stride), 128 per block / workgroup; the
# float32 + float64 33-wide sums live in registers (Vulkan: shaderFloat64); one [48] row per thread, no atomics.
@ti.kernel
def _reduce(src: f32_2, T: f32_2, tp: f32_2, tn: f32_2, idx: ti.types.ndarray(dtype=ti.i32, ndim=1), kind: ti.i32,
            k: ti.f32, has_photo: ti.i32, s_int: ti.types.ndarray(dtype=ti.f32, ndim=1), t_int: f32_2, t_gu: f32_2,
            t_gv: f32_2, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32, lam: ti.f32, projective: ti.i32, sn: f32_2,
            th: ti.i32, tw: ti.i32, max_d: ti.f32, cos_min: ti.f32, blocks: ti.i32,
            start_stride: ti.i32, item_stride: ti.i32, count: ti.i32, out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    # Same scheme as the Warp kernel: runs of SUB points summed in float32 over the upper triangle, flushed into
    # float64 per block; blocks run in parallel over the cores.
    n_pts = src.shape[0]
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: spread over the cores (kernels/_taichi/launch.py)
    for it in range(blocks * sp):
        if it % sp != 0:
            continue
        b = it // sp
        acc = ti.Vector.zero(ti.f64, 33)
        for s in range((count + SUB - 1) // SUB):
            part = ti.Vector.zero(ti.f32, 33)
            for kk in range(SUB):
                jj = s * SUB + kk
                i = b * start_stride + jj * item_stride
                t = -1
                p = ti.Vector([0.0, 0.0, 0.0])
                if i < n_pts and jj < count:
                    p = _xform(T, src[i, 0], src[i, 1], src[i, 2])
                    if projective != 0:
                        t = _project_assoc(ti.Vector([src[i, 0], src[i, 1], src[i, 2]]), p, T, tp, tn, sn, i, th, tw,
                                           fx, fy, cx, cy, max_d, cos_min)
                    else:
                        t = idx[i]
                if t >= 0:
                    q = ti.Vector([tp[t, 0], tp[t, 1], tp[t, 2]])
                    nq = ti.Vector([tn[t, 0], tn[t, 1], tn[t, 2]])
                    d = p - q
                    r = nq.dot(d)
                    c = p.cross(nq)
                    J = ti.Vector([c[0], c[1], c[2], nq[0], nq[1], nq[2]])
                    w = _robust_w(r, kind, k)
                    part += _contrib(J, w, r, w * r * r, d.norm_sqr(), 1.0, ti.abs(r), 0.0, 0.0)
                    if has_photo != 0:
                        hh, ww = t_int.shape[0], t_int.shape[1]
                        u = fx * p[0] / p[2] + cx
                        v = fy * p[1] / p[2] + cy
                        fu, fv = ti.floor(u), ti.floor(v)
                        if fu >= 0.0 and fv >= 0.0 and fu + 1.0 <= ti.cast(ww - 1, ti.f32) and fv + 1.0 <= ti.cast(hh - 1, ti.f32):
                            ri = lam * (_bilinear1(t_int, u, v) - s_int[i])
                            gu = _bilinear1(t_gu, u, v)
                            gv = _bilinear1(t_gv, u, v)
                            z = p[2]
                            dp = ti.Vector([gu * fx / z, gv * fy / z, -(gu * fx * p[0] + gv * fy * p[1]) / (z * z)])
                            cp = p.cross(dp)
                            JI = lam * ti.Vector([cp[0], cp[1], cp[2], dp[0], dp[1], dp[2]])
                            part += _contrib(JI, 1.0, ri, 0.0, 0.0, 0.0, 0.0, ri * ri, 1.0)
            acc += ti.cast(part, ti.f64)
        n = 0
        for r0 in ti.static(range(6)):
            for c0 in ti.static(range(r0, 6)):
                out[b, r0 * 6 + c0] = acc[n]
                out[b, c0 * 6 + r0] = acc[n]
                n += 1
        for q in ti.static(range(6)):
            out[b, 36 + q] = acc[21 + q]
        out[b, 42] = acc[27]
        out[b, 43] = acc[28]
        out[b, 44] = acc[29]
        out[b, 47] = acc[30]
        out[b, 45] = acc[31]
        out[b, 46] = acc[32]


def _sync(device: str) -> None:
    if device != "cpu":  # CUDA launches are asynchronous; on Vulkan the launch already waited (no-op)
        ti.sync()


def vertices_normals(depth: torch.Tensor, camera, jump: float, device: str):
    H, W = depth.shape
    verts = torch.empty(H, W, 3, dtype=torch.float32, device=depth.device)
    normals = torch.empty_like(verts)
    chunk = W if device == "cpu" else 1
    _vertices_normals(depth, 1.0 / camera.fx, 1.0 / camera.fy, camera.cx, camera.cy, jump, chunk, verts, normals)
    _sync(device)
    return verts, normals


class _Grid:
    """Points sorted by cell hash with per-bucket start/count; `reach` neighbour cells per side for a radius."""

    def __init__(self, points: torch.Tensor, cell: float):
        m = points.shape[0]
        size = 1 << max(4, math.ceil(math.log2(max(2 * m, 1))))
        self.mask = size - 1
        self.cell = cell
        cells = torch.floor(points / torch.tensor(cell, dtype=torch.float32, device=points.device)).to(torch.int64)
        h = ((cells[:, 0] * _P1) ^ (cells[:, 1] * _P2) ^ (cells[:, 2] * _P3)) & self.mask
        order = torch.argsort(h, stable=True)
        self.sorted_points = points[order].contiguous()
        self.sorted_cells = cells[order].to(torch.int32).contiguous()
        self.sorted_index = order.to(torch.int32).contiguous()
        count = torch.bincount(h, minlength=size)
        self.count = count.to(torch.int32).contiguous()
        self.start = (torch.cumsum(count, 0) - count).to(torch.int32).contiguous()

    def reach(self, radius: float) -> int:
        return max(1, math.ceil(radius / self.cell))


def build_grid(points: torch.Tensor, cell: float, device: str):
    return _Grid(points, cell)


def cloud_moments(grid: _Grid, points, queries, radius: float, device: str):
    out = torch.zeros(queries.shape[0], 10, dtype=torch.float64, device=queries.device)
    if queries.shape[0] and grid.sorted_points.shape[0]:
        _moments(grid.sorted_points, grid.sorted_cells, grid.start, grid.count, grid.cell, grid.mask,
                 grid.reach(radius), queries, radius, out)
        _sync(device)
    return out


def associate_nearest(grid: _Grid, points, src, T, max_d: float, device: str):
    out = torch.full((src.shape[0],), -1, dtype=torch.int32, device=src.device)
    if src.shape[0] and grid.sorted_points.shape[0]:
        _assoc_nearest(grid.sorted_points, grid.sorted_cells, grid.sorted_index, grid.start, grid.count, grid.cell,
                       grid.mask, grid.reach(max_d), src, T, max_d, out)
        _sync(device)
    return out


def associate_projective(src, T, tv, tn, sn, camera, max_d: float, cos_min: float, device: str):
    out = torch.empty(src.shape[0], dtype=torch.int32, device=src.device)
    if src.shape[0]:
        H, W = tv.shape[:2]
        _assoc_projective(src, T, tv.reshape(-1, 3), tn.reshape(-1, 3), sn, H, W, camera.fx, camera.fy, camera.cx,
                          camera.cy, max_d, cos_min, out)
        _sync(device)
    return out


def reduce_point_to_plane(src, T, tp, tn, idx, kind: int, k: float, photo, device: str, proj=None):
    """proj = (source_normals, camera, H, W, max_d, cos_min) fuses projective association into the pass (idx unused)."""
    n = src.shape[0]
    blocks, start_stride, item_stride, count = n_blocks(n, device)
    out = torch.zeros(blocks, N_SLOTS, dtype=torch.float64, device=src.device)
    r = reduce_terms(src, photo, proj)
    if n:
        _reduce(src, T, tp, tn, idx, kind, k, r.has_photo, r.s_int, r.t_int, r.gu, r.gv, r.fx, r.fy, r.cx, r.cy, r.lam,
                r.projective, r.sn, r.th, r.tw, r.max_d, r.cos_min, blocks, start_stride, item_stride, count, out)
        _sync(device)
    return out.sum(0)
