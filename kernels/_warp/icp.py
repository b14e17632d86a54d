"""Warp implementation of the ICP kernels (see `kernels/icp.py` for the contract, `kernels/_ref_icp.py` for
the twins). Neighbour search uses wp.HashGrid; reductions write one float64 row per block."""

from __future__ import annotations

import torch
import warp as wp

from ..icp import N_SLOTS, n_blocks

_DUMMY: dict = {}


@wp.func
def _backproject(d: float, u: int, v: int, fx: float, fy: float, cx: float, cy: float):
    return wp.vec3((float(u) - cx) / fx * d, (float(v) - cy) / fy * d, d)


@wp.kernel
def _vertices_normals(depth: wp.array2d(dtype=wp.float32), fx: float, fy: float, cx: float, cy: float, jump: float,
                      verts: wp.array2d(dtype=wp.vec3), normals: wp.array2d(dtype=wp.vec3)):
    v, u = wp.tid()
    H = depth.shape[0]
    W = depth.shape[1]
    d = depth[v, u]
    p = wp.vec3(0.0, 0.0, 0.0)
    if d > 0.0:
        p = _backproject(d, u, v, fx, fy, cx, cy)
    verts[v, u] = p
    n = wp.vec3(0.0, 0.0, 0.0)
    if d > 0.0 and u > 0 and v > 0 and u < W - 1 and v < H - 1:
        dr = depth[v, u + 1]
        dl = depth[v, u - 1]
        dd = depth[v + 1, u]
        du = depth[v - 1, u]
        lim = jump * d
        ok = dr > 0.0 and dl > 0.0 and dd > 0.0 and du > 0.0
        ok = ok and wp.abs(dr - d) <= lim and wp.abs(dl - d) <= lim and wp.abs(dd - d) <= lim and wp.abs(du - d) <= lim
        if ok:
            dx = _backproject(dr, u + 1, v, fx, fy, cx, cy) - _backproject(dl, u - 1, v, fx, fy, cx, cy)
            dy = _backproject(dd, u, v + 1, fx, fy, cx, cy) - _backproject(du, u, v - 1, fx, fy, cx, cy)
            c = wp.cross(dx, dy)
            ln = wp.length(c)
            if ln > 1.0e-12:
                n = c / ln
                if wp.dot(n, p) > 0.0:
                    n = -n
    normals[v, u] = n


@wp.kernel
def _moments(grid: wp.uint64, points: wp.array(dtype=wp.vec3), queries: wp.array(dtype=wp.vec3), radius: float,
             out: wp.array2d(dtype=wp.float64)):
    i = wp.tid()
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
def _xform(T: wp.array2d(dtype=wp.float32), p: wp.vec3):
    return wp.vec3(T[0, 0] * p[0] + T[0, 1] * p[1] + T[0, 2] * p[2] + T[0, 3],
                   T[1, 0] * p[0] + T[1, 1] * p[1] + T[1, 2] * p[2] + T[1, 3],
                   T[2, 0] * p[0] + T[2, 1] * p[1] + T[2, 2] * p[2] + T[2, 3])


@wp.func
def _rotate(T: wp.array2d(dtype=wp.float32), p: wp.vec3):
    return wp.vec3(T[0, 0] * p[0] + T[0, 1] * p[1] + T[0, 2] * p[2],
                   T[1, 0] * p[0] + T[1, 1] * p[1] + T[1, 2] * p[2],
                   T[2, 0] * p[0] + T[2, 1] * p[1] + T[2, 2] * p[2])


@wp.kernel
def _assoc_projective(src: wp.array(dtype=wp.vec3), T: wp.array2d(dtype=wp.float32),
                      tv: wp.array2d(dtype=wp.vec3), tn: wp.array2d(dtype=wp.vec3), sn: wp.array(dtype=wp.vec3),
                      fx: float, fy: float, cx: float, cy: float, max_d: float, cos_min: float,
                      out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = -1
    p = src[i]
    if p[2] <= 0.0:
        return
    q = _xform(T, p)
    if q[2] <= 0.0:
        return
    u = int(wp.floor(fx * q[0] / q[2] + cx + 0.5))
    v = int(wp.floor(fy * q[1] / q[2] + cy + 0.5))
    H = tv.shape[0]
    W = tv.shape[1]
    if u < 0 or v < 0 or u >= W or v >= H:
        return
    n = tn[v, u]
    if n[0] == 0.0 and n[1] == 0.0 and n[2] == 0.0:
        return
    if wp.length_sq(q - tv[v, u]) > max_d * max_d:
        return
    if cos_min >= -1.0:
        if wp.dot(_rotate(T, sn[i]), n) < cos_min:
            return
    out[i] = v * W + u


@wp.kernel
def _assoc_nearest(grid: wp.uint64, points: wp.array(dtype=wp.vec3), src: wp.array(dtype=wp.vec3),
                   T: wp.array2d(dtype=wp.float32), max_d: float, out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    q = _xform(T, src[i])
    best = max_d * max_d
    best_j = int(-1)
    query = wp.hash_grid_query(grid, q, max_d)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d2 = wp.length_sq(points[j] - q)
        if d2 < best or (d2 == best and (best_j < 0 or j < best_j)):
            best = d2
            best_j = j
    out[i] = best_j


@wp.func
def _bilinear1(img: wp.array2d(dtype=wp.float32), u: float, v: float):
    x0 = int(wp.floor(u))
    y0 = int(wp.floor(v))
    a = u - float(x0)
    b = v - float(y0)
    return (img[y0, x0] * (1.0 - a) * (1.0 - b) + img[y0, x0 + 1] * a * (1.0 - b)
            + img[y0 + 1, x0] * (1.0 - a) * b + img[y0 + 1, x0 + 1] * a * b)


@wp.func
def _robust_w(r: float, kind: int, k: float):
    a = wp.abs(r)
    if kind == 1:
        if a <= k:
            return 1.0
        return k / a
    if kind == 2:
        if a <= k:
            t = 1.0 - (r / k) * (r / k)
            return t * t
        return 0.0
    return 1.0


@wp.kernel
def _reduce(src: wp.array(dtype=wp.vec3), T: wp.array2d(dtype=wp.float32), tp: wp.array(dtype=wp.vec3),
            tn: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.int32), kind: int, k: float,
            has_photo: int, s_int: wp.array(dtype=wp.float32), t_int: wp.array2d(dtype=wp.float32),
            t_gu: wp.array2d(dtype=wp.float32), t_gv: wp.array2d(dtype=wp.float32),
            fx: float, fy: float, cx: float, cy: float, lam: float,
            start_stride: int, item_stride: int, count: int, out: wp.array2d(dtype=wp.float64)):
    b = wp.tid()
    n_pts = src.shape[0]
    H = wp.spatial_matrixd()
    g = wp.spatial_vectord()
    cost = wp.float64(0.0)
    dist = wp.float64(0.0)
    cnt = wp.float64(0.0)
    pcost = wp.float64(0.0)
    pcnt = wp.float64(0.0)
    absr = wp.float64(0.0)
    for jj in range(count):
        i = b * start_stride + jj * item_stride
        if i < n_pts:
            t = idx[i]
            if t >= 0:
                p = _xform(T, src[i])
                q = tp[t]
                nq = tn[t]
                r = wp.dot(nq, p - q)
                c = wp.cross(p, nq)
                J = wp.spatial_vectord(wp.float64(c[0]), wp.float64(c[1]), wp.float64(c[2]),
                                       wp.float64(nq[0]), wp.float64(nq[1]), wp.float64(nq[2]))
                w = wp.float64(_robust_w(r, kind, k))
                rd = wp.float64(r)
                H += wp.outer(J, J * w)
                g += J * (w * rd)
                cost += w * rd * rd
                dist += wp.float64(wp.length_sq(p - q))
                cnt += wp.float64(1.0)
                absr += wp.abs(rd)
                if has_photo != 0:
                    hh = t_int.shape[0]
                    ww = t_int.shape[1]
                    u = fx * p[0] / p[2] + cx
                    v = fy * p[1] / p[2] + cy
                    fu = wp.floor(u)
                    fv = wp.floor(v)
                    if fu >= 0.0 and fv >= 0.0 and fu + 1.0 <= float(ww - 1) and fv + 1.0 <= float(hh - 1):
                        ri = lam * (_bilinear1(t_int, u, v) - s_int[i])
                        gu = _bilinear1(t_gu, u, v)
                        gv = _bilinear1(t_gv, u, v)
                        z = p[2]
                        dp = wp.vec3(gu * fx / z, gv * fy / z, -(gu * fx * p[0] + gv * fy * p[1]) / (z * z))
                        cp = wp.cross(p, dp)
                        JI = wp.spatial_vectord(wp.float64(cp[0]), wp.float64(cp[1]), wp.float64(cp[2]),
                                                wp.float64(dp[0]), wp.float64(dp[1]), wp.float64(dp[2])) * wp.float64(lam)
                        rid = wp.float64(ri)
                        H += wp.outer(JI, JI)
                        g += JI * rid
                        pcost += rid * rid
                        pcnt += wp.float64(1.0)
    for a in range(6):
        for c2 in range(6):
            out[b, a * 6 + c2] = H[a, c2]
        out[b, 36 + a] = g[a]
    out[b, 42] = cost
    out[b, 43] = dist
    out[b, 44] = cnt
    out[b, 45] = pcost
    out[b, 46] = pcnt
    out[b, 47] = absr


def _sync(device: str) -> None:
    if device == "cuda":
        wp.synchronize_device(device)


def vertices_normals(depth: torch.Tensor, camera, jump: float, device: str):
    H, W = depth.shape
    verts = torch.empty(H, W, 3, dtype=torch.float32, device=depth.device)
    normals = torch.empty_like(verts)
    wp.launch(_vertices_normals, dim=(H, W), device=device,
              inputs=[wp.from_torch(depth), camera.fx, camera.fy, camera.cx, camera.cy, jump,
                      wp.from_torch(verts, dtype=wp.vec3), wp.from_torch(normals, dtype=wp.vec3)])
    _sync(device)
    return verts, normals


class _Grid:
    def __init__(self, points: torch.Tensor, cell: float, device: str):
        self.wp_points = wp.from_torch(points, dtype=wp.vec3)
        self.grid = wp.HashGrid(128, 128, 128, device=device)
        self.grid.build(self.wp_points, cell)


def build_grid(points: torch.Tensor, cell: float, device: str):
    return _Grid(points, cell, device)


def cloud_moments(grid: _Grid, points: torch.Tensor, queries: torch.Tensor, radius: float, device: str):
    out = torch.zeros(queries.shape[0], 10, dtype=torch.float64, device=queries.device)
    if queries.shape[0]:
        wp.launch(_moments, dim=queries.shape[0], device=device,
                  inputs=[grid.grid.id, grid.wp_points, wp.from_torch(queries, dtype=wp.vec3), radius, wp.from_torch(out)])
        _sync(device)
    return out


def associate_projective(src, T, tv, tn, sn, camera, max_d: float, cos_min: float, device: str):
    out = torch.empty(src.shape[0], dtype=torch.int32, device=src.device)
    if src.shape[0]:
        wp.launch(_assoc_projective, dim=src.shape[0], device=device,
                  inputs=[wp.from_torch(src, dtype=wp.vec3), wp.from_torch(T), wp.from_torch(tv, dtype=wp.vec3),
                          wp.from_torch(tn, dtype=wp.vec3), wp.from_torch(sn, dtype=wp.vec3),
                          camera.fx, camera.fy, camera.cx, camera.cy, max_d, cos_min, wp.from_torch(out)])
        _sync(device)
    return out


def associate_nearest(grid: _Grid, points, src, T, max_d: float, device: str):
    out = torch.empty(src.shape[0], dtype=torch.int32, device=src.device)
    if src.shape[0]:
        wp.launch(_assoc_nearest, dim=src.shape[0], device=device,
                  inputs=[grid.grid.id, grid.wp_points, wp.from_torch(src, dtype=wp.vec3), wp.from_torch(T), max_d,
                          wp.from_torch(out)])
        _sync(device)
    return out


def _dummies(dev: torch.device):
    key = str(dev)
    if key not in _DUMMY:
        _DUMMY[key] = (torch.zeros(1, dtype=torch.float32, device=dev), torch.zeros(2, 2, dtype=torch.float32, device=dev))
    return _DUMMY[key]


def reduce_point_to_plane(src, T, tp, tn, idx, kind: int, k: float, photo, device: str):
    n = src.shape[0]
    blocks, start_stride, item_stride, count = n_blocks(n, device)
    out = torch.zeros(blocks, N_SLOTS, dtype=torch.float64, device=src.device)
    if photo is None:
        s1, i2 = _dummies(src.device)
        s_int, t_int, gu, gv, fx, fy, cx, cy, lam, has = s1, i2, i2, i2, 1.0, 1.0, 0.0, 0.0, 0.0, 0
    else:
        s_int, t_int, grad, cam, lam = photo
        gu, gv = grad[..., 0].contiguous(), grad[..., 1].contiguous()
        fx, fy, cx, cy, has = cam.fx, cam.fy, cam.cx, cam.cy, 1
    if n:
        wp.launch(_reduce, dim=blocks, device=device,
                  inputs=[wp.from_torch(src, dtype=wp.vec3), wp.from_torch(T), wp.from_torch(tp, dtype=wp.vec3),
                          wp.from_torch(tn, dtype=wp.vec3), wp.from_torch(idx), kind, k, has, wp.from_torch(s_int),
                          wp.from_torch(t_int), wp.from_torch(gu), wp.from_torch(gv), fx, fy, cx, cy, lam,
                          start_stride, item_stride, count, wp.from_torch(out)])
        _sync(device)
    return out.sum(0)
