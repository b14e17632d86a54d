"""NumPy twins (float64) of the ICP kernels in `kernels.icp`: the specification the Warp and Taichi kernels are
tested against. Slow and obvious on purpose; never the production path.

Twins take and return torch tensors like the kernels (results as float64 / int32 on the CPU) so tests can
compare them directly. Conventions are those of `kernels.icp` (read its module docstring).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from .camera import PinholeCamera

ROBUST = {"none": 0, "huber": 1, "tukey": 2}
N_SLOTS = 48  # layout of the packed normal-equation sums, see kernels.icp.NormalEquations


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64) if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)


def vertices_normals_from_depth_ref(depth, camera: PinholeCamera, max_depth_jump: float = 0.05):
    """depth [H, W] metres (0 invalid) -> (vertices [H, W, 3], normals [H, W, 3]), float64.

    A normal is the normalised cross product of central differences, needs all four 4-neighbours valid and
    each within `max_depth_jump * depth` of the centre (a relative gate, so it scales with range), and points
    towards the camera. Invalid normals are 0.
    """
    d = _np(depth)
    H, W = d.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    P = np.stack([(u - camera.cx) / camera.fx * d, (v - camera.cy) / camera.fy * d, d], axis=-1)
    P[d <= 0] = 0.0
    N = np.zeros_like(P)
    c = d[1:-1, 1:-1]
    nb = [d[1:-1, 2:], d[1:-1, :-2], d[2:, 1:-1], d[:-2, 1:-1]]
    ok = c > 0
    for x in nb:
        ok &= (x > 0) & (np.abs(x - c) <= max_depth_jump * c)
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(dx, dy)
    ln = np.linalg.norm(n, axis=-1, keepdims=True)
    ok &= ln[..., 0] > 1e-12
    n = n / np.where(ln > 0, ln, 1.0)
    flip = np.sum(n * P[1:-1, 1:-1], axis=-1) > 0
    n[flip] *= -1.0
    n[~ok] = 0.0
    N[1:-1, 1:-1] = n
    return torch.from_numpy(P), torch.from_numpy(N)


def cloud_moments_ref(points, queries, radius: float):
    """For each query: count, sum and sum of outer products of the points within `radius` (inclusive).

    -> [Q, 10] float64: count, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz.
    """
    P, Q = _np(points), _np(queries)
    tree = cKDTree(P)
    out = np.zeros((len(Q), 10))
    for i, nbrs in enumerate(tree.query_ball_point(Q, r=radius)):
        X = P[nbrs]
        out[i, 0] = len(nbrs)
        out[i, 1:4] = X.sum(0)
        C = X.T @ X
        out[i, 4:] = C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2]
    return torch.from_numpy(out)


def normals_from_moments_ref(moments, points, viewpoint=None, min_neighbors: int = 3):
    """[Q, 10] moments -> [Q, 3] unit normals (smallest-eigenvalue eigenvector of the neighbour covariance),
    oriented towards `viewpoint` when given; 0 where fewer than `min_neighbors` points."""
    m = _np(moments)
    n = np.maximum(m[:, 0:1], 1.0)
    mean = m[:, 1:4] / n
    C = np.empty((len(m), 3, 3))
    idx = [(0, 0, 4), (0, 1, 5), (0, 2, 6), (1, 1, 7), (1, 2, 8), (2, 2, 9)]
    for a, b, k in idx:
        C[:, a, b] = C[:, b, a] = m[:, k] / n[:, 0] - mean[:, a] * mean[:, b]
    _, vecs = np.linalg.eigh(C)
    normals = vecs[:, :, 0]
    if viewpoint is not None:
        to_view = np.asarray(viewpoint, np.float64)[None] - _np(points)
        normals[np.sum(normals * to_view, axis=1) < 0] *= -1.0
    normals[m[:, 0] < min_neighbors] = 0.0
    return torch.from_numpy(normals)


def _transform(T, p):
    T = _np(T)
    return p @ T[:3, :3].T + T[:3, 3]


def associate_projective_ref(source_points, T_target_source, target_vertices, target_normals, camera: PinholeCamera,
                             max_distance: float, source_normals=None, min_cos_angle: float = -2.0):
    """Projective data association -> int32 [N]: flat target pixel index (v * W + u) or -1.

    Source point p (source frame, z > 0 means valid) moves to p' = T p, projects to the nearest pixel
    (floor(x + 0.5)); it is kept when the pixel is inside the image, its target normal is non-zero, the
    Euclidean distance |p' - q| <= max_distance and, when source normals are given, R n_s . n_t >= min_cos_angle.
    """
    P = _np(source_points)
    Vt = _np(target_vertices)
    Nt = _np(target_normals)
    H, W = Vt.shape[:2]
    q = _transform(T_target_source, P)
    out = -np.ones(len(P), np.int32)
    valid = (P[:, 2] > 0) & (q[:, 2] > 0)
    z = np.where(valid, q[:, 2], 1.0)
    u = np.floor(camera.fx * q[:, 0] / z + camera.cx + 0.5)
    v = np.floor(camera.fy * q[:, 1] / z + camera.cy + 0.5)
    valid &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
    ui = np.where(valid, u, 0).astype(np.int64)
    vi = np.where(valid, v, 0).astype(np.int64)
    tq, tn = Vt[vi, ui], Nt[vi, ui]
    valid &= np.any(tn != 0, axis=1)
    valid &= np.sum((q - tq) ** 2, axis=1) <= max_distance**2
    if source_normals is not None:
        Rn = _np(source_normals) @ _np(T_target_source)[:3, :3].T
        valid &= np.sum(Rn * tn, axis=1) >= min_cos_angle
    out[valid] = (vi * W + ui)[valid].astype(np.int32)
    return torch.from_numpy(out)


def associate_nearest_ref(source_points, T_target_source, target_points, max_distance: float):
    """Nearest target point within max_distance (inclusive) of each transformed source point -> int32 [N] or -1."""
    q = _transform(T_target_source, _np(source_points))
    d, i = cKDTree(_np(target_points)).query(q, k=1, distance_upper_bound=max_distance)
    out = np.where(np.isfinite(d) & (d <= max_distance), i, -1).astype(np.int32)
    return torch.from_numpy(out)


def robust_weight_ref(r: np.ndarray, kind: str, k: float) -> np.ndarray:
    """Huber: 1 inside k, k/|r| outside. Tukey: (1 - (r/k)^2)^2 inside k, 0 outside. none: 1."""
    a = np.abs(r)
    if kind == "huber":
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
    if kind == "tukey":
        return np.where(a <= k, (1.0 - (r / k) ** 2) ** 2, 0.0)
    return np.ones_like(r)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Bilinear samples of img [H, W, ...] at (u, v); ok where all four taps are inside."""
    H, W = img.shape[:2]
    u0, v0 = np.floor(u), np.floor(v)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 + 1 <= W - 1) & (v0 + 1 <= H - 1)
    a, b = u - u0, v - v0
    x0 = np.where(ok, u0, 0).astype(np.int64)
    y0 = np.where(ok, v0, 0).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    a = a.reshape(a.shape + (1,) * (img.ndim - 2))
    b = b.reshape(b.shape + (1,) * (img.ndim - 2))
    val = (img[y0, x0] * (1 - a) * (1 - b) + img[y0, x1] * a * (1 - b) + img[y1, x0] * (1 - a) * b
           + img[y1, x1] * a * b)
    return val, ok


def reduce_point_to_plane_ref(source_points, T_target_source, target_points, target_normals, idx,
                              robust: str = "none", robust_scale: float = 0.0, photometric=None):
    """Point-to-plane normal equations -> float64 [48] packed sums (layout in kernels.icp.NormalEquations).

    Residual r = n_q . (T p - q); Jacobian wrt a left twist [omega, v] (T <- exp(xi) T): J = [p' x n, n].
    Robust weight w(r) from `robust`/`robust_scale`. With `photometric = (source_intensity [N],
    target_intensity [H, W], target_gradient [H, W, 2], camera, weight)`, each inlier adds
    r_I = I_t(pi(p')) - I_s(p) (bilinear, all taps inside) with J_I = dI/duv . dpi/dp' . [-[p']x, I], both
    scaled by `weight`.
    """
    P = _np(source_points)
    Q = _np(target_points)
    Nq = _np(target_normals)
    idx = _np(idx).astype(np.int64)
    m = idx >= 0
    p = _transform(T_target_source, P[m])
    q, n = Q[idx[m]], Nq[idx[m]]
    r = np.sum(n * (p - q), axis=1)
    J = np.concatenate([np.cross(p, n), n], axis=1)
    w = robust_weight_ref(r, robust, robust_scale)
    out = np.zeros(N_SLOTS)
    out[0:36] = (J.T @ (J * w[:, None])).reshape(-1)
    out[36:42] = J.T @ (w * r)
    out[42] = np.sum(w * r * r)
    out[43] = np.sum((p - q) ** 2)
    out[44] = m.sum()
    out[47] = np.sum(np.abs(r))
    if photometric is not None:
        Is, It, G, cam, lam = photometric
        Is, It, G = _np(Is)[m], _np(It), _np(G)
        z = p[:, 2]
        u = cam.fx * p[:, 0] / z + cam.cx
        v = cam.fy * p[:, 1] / z + cam.cy
        it, ok1 = _bilinear(It, u, v)
        g, ok2 = _bilinear(G, u, v)
        ok = ok1 & ok2
        rI = lam * (it - Is)
        gu, gv = g[:, 0], g[:, 1]
        # d(u, v)/dp' then dp'/dxi = [-[p']x, I]  ->  dI/dxi = (dI/dp') . [-[p']x, I] = [p' x dI/dp', dI/dp']
        dIdp = np.stack([gu * cam.fx / z, gv * cam.fy / z, -(gu * cam.fx * p[:, 0] + gv * cam.fy * p[:, 1]) / z**2], 1)
        JI = lam * np.concatenate([np.cross(p, dIdp), dIdp], axis=1)
        JI, rI = JI[ok], rI[ok]
        out[0:36] += (JI.T @ JI).reshape(-1)
        out[36:42] += JI.T @ rI
        out[45] = np.sum(rI * rI)
        out[46] = ok.sum()
    return torch.from_numpy(out)
