"""Warp kernels of the EWA projection (one thread per Gaussian) and its hand-written backward.

Forward writes one row per Gaussian: mean2d x, y, conic a, b, c, opacity, r, g, b, z (kernels.raster.PACKED),
plus the 3-sigma radius and the tile rectangle; culled Gaussians get zeros. Backward turns the row gradients into
gradients of means, quats (through the normalisation), scales and a per-Gaussian [12] slice of the viewmat
gradient (rotation row-major, then translation), summed by the caller. The math is in kernels/_ref_raster.py.
"""

from __future__ import annotations

import warp as wp

from .raster import launch_chunked, to_warp

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

TILE = 16


@wp.func
def _rotmat(w: float, x: float, y: float, z: float) -> wp.mat33:
    return wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                    2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                    2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@wp.func
def _view_rot(view: wp.array2d(dtype=float)) -> wp.mat33:
    return wp.mat33(view[0, 0], view[0, 1], view[0, 2], view[1, 0], view[1, 1], view[1, 2],
                    view[2, 0], view[2, 1], view[2, 2])


@wp.kernel
def _project_fwd(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                 opac: wp.array(dtype=float), colors: wp.array2d(dtype=float), view: wp.array2d(dtype=float),
                 fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                 offset: int, proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
                 rect: wp.array2d(dtype=wp.int32)):
    i = wp.tid() + offset
    for k in range(10):
        proj[i, k] = 0.0
    for k in range(4):
        rect[i, k] = 0
    radius[i] = 0
    Rv = _view_rot(view)
    p = wp.mul(Rv, wp.vec3(means[i, 0], means[i, 1], means[i, 2])) + wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    z = p[2]
    if z < near or z > far:
        return
    inv_z = 1.0 / z
    lim_x = 0.15 * float(width) / fx
    lim_y = 0.15 * float(height) / fy
    u = wp.clamp(p[0] * inv_z, -(cx / fx + lim_x), (float(width) - cx) / fx + lim_x)
    v = wp.clamp(p[1] * inv_z, -(cy / fy + lim_y), (float(height) - cy) / fy + lim_y)
    qw = quats[i, 0]
    qx = quats[i, 1]
    qy = quats[i, 2]
    qz = quats[i, 3]
    qn = 1.0 / wp.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    N = wp.mul(Rv, _rotmat(qw * qn, qx * qn, qy * qn, qz * qn))
    Mc = wp.mul(N, wp.diag(wp.vec3(scales[i, 0], scales[i, 1], scales[i, 2])))
    T0 = fx * inv_z * (Mc[0] - u * Mc[2])
    T1 = fy * inv_z * (Mc[1] - v * Mc[2])
    a = wp.dot(T0, T0) + 0.3
    b = wp.dot(T0, T1)
    c = wp.dot(T1, T1) + 0.3
    det = a * c - b * b
    if det <= 0.0:
        return
    mx = fx * p[0] * inv_z + cx
    my = fy * p[1] * inv_z + cy
    mid = 0.5 * (a + c)
    r = wp.ceil(3.0 * wp.sqrt(mid + wp.sqrt(wp.max(mid * mid - det, 0.1))))
    ntx = float((width + TILE - 1) // TILE)
    nty = float((height + TILE - 1) // TILE)
    x0 = wp.clamp(wp.floor((mx - r) / float(TILE)), 0.0, ntx)
    x1 = wp.clamp(wp.floor((mx + r) / float(TILE)) + 1.0, 0.0, ntx)
    y0 = wp.clamp(wp.floor((my - r) / float(TILE)), 0.0, nty)
    y1 = wp.clamp(wp.floor((my + r) / float(TILE)) + 1.0, 0.0, nty)
    if x1 <= x0 or y1 <= y0:
        return
    inv_det = 1.0 / det
    proj[i, 0] = mx
    proj[i, 1] = my
    proj[i, 2] = c * inv_det
    proj[i, 3] = -b * inv_det
    proj[i, 4] = a * inv_det
    proj[i, 5] = opac[i]
    proj[i, 6] = colors[i, 0]
    proj[i, 7] = colors[i, 1]
    proj[i, 8] = colors[i, 2]
    proj[i, 9] = z
    radius[i] = int(wp.min(r, 1073741824.0))
    rect[i, 0] = int(x0)
    rect[i, 1] = int(y0)
    rect[i, 2] = int(x1)
    rect[i, 3] = int(y1)


@wp.kernel
def _project_bwd(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                 view: wp.array2d(dtype=float), fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                 offset: int, proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
                 g_proj: wp.array2d(dtype=float), g_means: wp.array2d(dtype=float), g_quats: wp.array2d(dtype=float),
                 g_scales: wp.array2d(dtype=float), g_view: wp.array2d(dtype=float)):
    i = wp.tid() + offset
    for k in range(3):
        g_means[i, k] = 0.0
        g_scales[i, k] = 0.0
    for k in range(4):
        g_quats[i, k] = 0.0
    for k in range(12):
        g_view[i, k] = 0.0
    if radius[i] == 0:
        return
    # Recompute the forward intermediates (cheaper than storing them).
    Rv = _view_rot(view)
    m = wp.vec3(means[i, 0], means[i, 1], means[i, 2])
    p = wp.mul(Rv, m) + wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    inv_z = 1.0 / p[2]
    lim_x = 0.15 * float(width) / fx
    lim_y = 0.15 * float(height) / fy
    ru = p[0] * inv_z
    rv = p[1] * inv_z
    u = wp.clamp(ru, -(cx / fx + lim_x), (float(width) - cx) / fx + lim_x)
    v = wp.clamp(rv, -(cy / fy + lim_y), (float(height) - cy) / fy + lim_y)
    qw = quats[i, 0]
    qx = quats[i, 1]
    qy = quats[i, 2]
    qz = quats[i, 3]
    qlen = wp.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    w = qw / qlen
    x = qx / qlen
    y = qy / qlen
    z = qz / qlen
    Rq = _rotmat(w, x, y, z)
    N = wp.mul(Rv, Rq)
    s = wp.vec3(scales[i, 0], scales[i, 1], scales[i, 2])
    Mc = wp.mul(N, wp.diag(s))
    f0 = fx * inv_z
    f1 = fy * inv_z
    T0 = f0 * (Mc[0] - u * Mc[2])
    T1 = f1 * (Mc[1] - v * Mc[2])
    # conic = inverse(cov2d): dL/dcov2d = -Q G Q (b counted on both off-diagonals)
    A = proj[i, 2]
    B = proj[i, 3]
    C = proj[i, 4]
    gA = g_proj[i, 2]
    gB = g_proj[i, 3]
    gC = g_proj[i, 4]
    ga = -(A * A * gA + A * B * gB + B * B * gC)
    gb = -(2.0 * A * B * gA + (A * C + B * B) * gB + 2.0 * B * C * gC)
    gc = -(B * B * gA + B * C * gB + C * C * gC)
    gT0 = 2.0 * ga * T0 + gb * T1
    gT1 = gb * T0 + 2.0 * gc * T1
    gM0 = f0 * gT0
    gM1 = f1 * gT1
    gM2 = -(u * f0) * gT0 - (v * f1) * gT1
    g_inv_z = (wp.dot(gT0, T0) + wp.dot(gT1, T1)) * p[2]
    g_mx = g_proj[i, 0]
    g_my = g_proj[i, 1]
    gx = g_mx * f0
    gy = g_my * f1
    g_inv_z += g_mx * fx * p[0] + g_my * fy * p[1]
    if ru == u:  # the 1.3 x field-of-view clamp passes gradients only where it is not active
        gu = -f0 * wp.dot(gT0, Mc[2])
        gx += gu * inv_z
        g_inv_z += gu * p[0]
    if rv == v:
        gv = -f1 * wp.dot(gT1, Mc[2])
        gy += gv * inv_z
        g_inv_z += gv * p[1]
    gz = g_proj[i, 9] - g_inv_z * inv_z * inv_z
    gp = wp.vec3(gx, gy, gz)
    gMc = wp.mat33(gM0[0], gM0[1], gM0[2], gM1[0], gM1[1], gM1[2], gM2[0], gM2[1], gM2[2])
    gN = wp.mul(gMc, wp.diag(s))
    for j in range(3):
        g_scales[i, j] = gMc[0, j] * N[0, j] + gMc[1, j] * N[1, j] + gMc[2, j] * N[2, j]
    G = wp.mul(wp.transpose(Rv), gN)  # dL/dRq
    gw = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
    gxq = 2.0 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2.0 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                 + w * G[2, 1] - 2.0 * x * G[2, 2])
    gyq = 2.0 * (-2.0 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                 + z * G[2, 1] - 2.0 * y * G[2, 2])
    gzq = 2.0 * (-2.0 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2.0 * z * G[1, 1] + y * G[1, 2]
                 + x * G[2, 0] + y * G[2, 1])
    dot = w * gw + x * gxq + y * gyq + z * gzq
    g_quats[i, 0] = (gw - w * dot) / qlen
    g_quats[i, 1] = (gxq - x * dot) / qlen
    g_quats[i, 2] = (gyq - y * dot) / qlen
    g_quats[i, 3] = (gzq - z * dot) / qlen
    gm = wp.mul(wp.transpose(Rv), gp)
    g_means[i, 0] = gm[0]
    g_means[i, 1] = gm[1]
    g_means[i, 2] = gm[2]
    gRv = wp.mul(gN, wp.transpose(Rq)) + wp.outer(gp, m)
    for r in range(3):
        for j in range(3):
            g_view[i, 3 * r + j] = gRv[r, j]
        g_view[i, 9 + r] = gp[r]


def project_forward(means, quats, scales, opac, colors, view, intr, width, height, near, far, proj, radius, rect,
                    device) -> None:
    n = means.shape[0]
    if n == 0:
        return
    fx, fy, cx, cy = intr
    inputs = [to_warp(means), to_warp(quats), to_warp(scales), to_warp(opac), to_warp(colors), to_warp(view),
              fx, fy, cx, cy, width, height, near, far, 0, to_warp(proj), to_warp(radius), to_warp(rect)]
    launch_chunked(_project_fwd, n, inputs, 14, device)


def project_backward(means, quats, scales, view, intr, width, height, proj, radius, g_proj, g_means, g_quats,
                     g_scales, g_view, device) -> None:
    n = means.shape[0]
    if n == 0:
        return
    fx, fy, cx, cy = intr
    inputs = [to_warp(means), to_warp(quats), to_warp(scales), to_warp(view), fx, fy, cx, cy, width, height, 0,
              to_warp(proj), to_warp(radius), to_warp(g_proj), to_warp(g_means), to_warp(g_quats), to_warp(g_scales),
              to_warp(g_view)]
    launch_chunked(_project_bwd, n, inputs, 10, device)
