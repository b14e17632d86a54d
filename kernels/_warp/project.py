"""Warp kernels of the EWA projection (one thread per Gaussian on CUDA, per BLOCK Gaussians on the CPU) and its
hand-written backward.

Forward writes one row per Gaussian: mean2d x, y, conic a, b, c, opacity, r, g, b, z (kernels.raster.PACKED),
the 3-sigma radius, the tile rectangle, the number of tiles touched and the exp() skip threshold
pthr = -ln(255 o) - 1e-5 (power below it cannot give alpha >= 1/255); culled Gaussians get zeros, invalid inputs
(non-finite, zero-length quaternion, opacity outside [0, 1]) get ntiles = -1 so the caller can name them.
Backward first sums the Gaussian's per-tile-entry gradients (kernels/_warp/sort.py lists them), then turns the
row gradient into gradients of means, quats (through the normalisation), scales, opacity, colour and a
[12] viewmat gradient (rotation row-major, then translation) per Gaussian (CUDA) or per block of 256 (CPU, summed
in the thread in index order), which _view_grad sums.
The math is in kernels/_ref_raster.py. On the CPU the same rules run as branch-free vector code
(kernels/_warp/project_cpu.py, CPU_PROJECT below); these kernels are the CUDA ones and the CPU's scalar peer.
"""

from __future__ import annotations

import warp as wp

from . import project_cpu as _cpu
from .arrays import to_warp
from .launch import launch, run

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

TILE = 16
# CPU: one kernel thread projects BLOCK consecutive Gaussians (a Warp CPU launch pays per thread: the argument
# struct is copied and the arrays' shapes re-read each time), and the backward sums a block's viewmat parts in
# the thread (in index order: the sums of _view_grad's blocks, bit for bit). CUDA: one thread per Gaussian.
BLOCK = 256
# "vector": the CPU projects with kernels/_warp/project_cpu.py (same rules, branch-free vector code); "scalar": with
# the kernels below (the CUDA ones; kept on the CPU as a peer and for tests)
CPU_PROJECT = "vector"

# CPU only (a no-op on CUDA): fetch into cache the tile-entry gradient rows of Gaussian i + 2, which the backward
# gathers next on this thread; they are scattered over the entry array (depth order), and the misses were a third
# of the backward's time at 320x240 / 60k Gaussians.
_PREFETCH_ENTRIES = r"""
#if !defined(__CUDA_ARCH__)
    const int j = i + 2;
    if (j < ntiles.shape[0]) {
        const int nt = *(const int*)((const char*)ntiles.data + (size_t)j * ntiles.strides[0]);
        const int k0 = *(const int*)((const char*)emit_start.data + (size_t)j * emit_start.strides[0]);
        for (int k = k0; k < k0 + (nt < 8 ? nt : 8); ++k) {
            const int e = *(const int*)((const char*)emit_pos.data + (size_t)k * emit_pos.strides[0]);
            const char* row = (const char*)g_entry.data + (size_t)e * g_entry.strides[0];
            __builtin_prefetch(row);
            __builtin_prefetch(row + 9 * g_entry.strides[1]);
        }
    }
#endif
"""


@wp.func_native(_PREFETCH_ENTRIES)
def _prefetch_entries(ntiles: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32),
                      emit_pos: wp.array(dtype=wp.int32), g_entry: wp.array2d(dtype=float), i: int):
    ...


@wp.func
def _rotmat(w: float, x: float, y: float, z: float) -> wp.mat33:
    return wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                    2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                    2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@wp.func
def _view_rot(view: wp.array2d(dtype=float)) -> wp.mat33:
    return wp.mat33(view[0, 0], view[0, 1], view[0, 2], view[1, 0], view[1, 1], view[1, 2],
                    view[2, 0], view[2, 1], view[2, 2])


@wp.func
def _finite(x: float) -> bool:
    # wp.isfinite without its out-of-line call (13 per Gaussian): false for NaN (no comparison holds) and +-Inf
    return wp.abs(x) <= 3.4028234663852886e38


@wp.func
def _cull(proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
          ntiles: wp.array(dtype=wp.int32), pthr: wp.array(dtype=float), i: int, nt: int):
    # a culled Gaussian's outputs: zeros, ntiles = nt (0, or -1 for invalid input)
    for k in range(10):
        proj[i, k] = 0.0
    for k in range(4):
        rect[i, k] = 0
    radius[i] = 0
    ntiles[i] = nt
    pthr[i] = 0.0


@wp.func
def _project_one(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                 opac: wp.array(dtype=float), colors: wp.array2d(dtype=float), Rv: wp.mat33, tv: wp.vec3,
                 fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                 proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                 ntiles: wp.array(dtype=wp.int32), pthr: wp.array(dtype=float), i: int):
    # every return path writes all of Gaussian i's outputs
    ok = _finite(opac[i]) and opac[i] >= 0.0 and opac[i] <= 1.0
    qlen2 = float(0.0)
    for k in range(3):
        ok = ok and _finite(means[i, k]) and _finite(scales[i, k]) and _finite(colors[i, k])
    for k in range(4):
        ok = ok and _finite(quats[i, k])
        qlen2 += quats[i, k] * quats[i, k]
    if not ok or qlen2 < 1e-20:
        _cull(proj, radius, rect, ntiles, pthr, i, -1)
        return
    p = wp.mul(Rv, wp.vec3(means[i, 0], means[i, 1], means[i, 2])) + tv
    z = p[2]
    if z < near or z > far:
        _cull(proj, radius, rect, ntiles, pthr, i, 0)
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
        _cull(proj, radius, rect, ntiles, pthr, i, 0)
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
        _cull(proj, radius, rect, ntiles, pthr, i, 0)
        return
    # the tiles listed: the radius' rectangle cut to the box of the alpha >= 1/255 ellipse (widened as the
    # compositing widens it; pixel centres at integers), which no composited pixel leaves: a low-opacity
    # Gaussian's is much smaller
    lo = -wp.log(255.0 * opac[i]) - 1e-5
    if lo < 0.0:
        lgm = -1.01 * lo + 0.01
        ex = wp.sqrt(2.0 * lgm * a)
        ey = wp.sqrt(2.0 * lgm * c)
        x0 = wp.max(x0, wp.floor(wp.ceil(mx - ex) / float(TILE)))
        x1 = wp.min(x1, wp.floor(wp.floor(mx + ex) / float(TILE)) + 1.0)
        y0 = wp.max(y0, wp.floor(wp.ceil(my - ey) / float(TILE)))
        y1 = wp.min(y1, wp.floor(wp.floor(my + ey) / float(TILE)) + 1.0)
    if lo >= 0.0 or x1 <= x0 or y1 <= y0:
        x0 = 0.0
        x1 = 0.0
        y0 = 0.0
        y1 = 0.0
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
    ntiles[i] = (int(x1) - int(x0)) * (int(y1) - int(y0))
    pthr[i] = lo


@wp.kernel
def _project_fwd(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                 opac: wp.array(dtype=float), colors: wp.array2d(dtype=float), view: wp.array2d(dtype=float),
                 fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                 offset: int, count: int, n: int, proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
                 rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), pthr: wp.array(dtype=float)):
    # CUDA: one thread per Gaussian (count 1): 80 registers per thread (sm_86, perf/gpu_codegen.py; main's kernel
    # 86), where the CPU's loop over blocks below takes 94
    i = wp.tid() + offset
    _project_one(means, quats, scales, opac, colors, _view_rot(view), wp.vec3(view[0, 3], view[1, 3], view[2, 3]),
                 fx, fy, cx, cy, width, height, near, far, proj, radius, rect, ntiles, pthr, i)


@wp.kernel
def _project_fwd_blocks(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float),
                        scales: wp.array2d(dtype=float), opac: wp.array(dtype=float), colors: wp.array2d(dtype=float),
                        view: wp.array2d(dtype=float), fx: float, fy: float, cx: float, cy: float, width: int,
                        height: int, near: float, far: float, offset: int, count: int, n: int,
                        proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
                        rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32),
                        pthr: wp.array(dtype=float)):
    # CPU: thread = Gaussians [count (tid + offset), + count) (see BLOCK)
    i0 = (wp.tid() + offset) * count
    Rv = _view_rot(view)
    tv = wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    for i in range(i0, wp.min(i0 + count, n)):
        _project_one(means, quats, scales, opac, colors, Rv, tv, fx, fy, cx, cy, width, height, near, far, proj,
                     radius, rect, ntiles, pthr, i)


@wp.func
def _project_bwd_one(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float),
                     scales: wp.array2d(dtype=float), Rv: wp.mat33, tv: wp.vec3, fx: float, fy: float, cx: float,
                     cy: float, width: int, height: int, proj: wp.array2d(dtype=float),
                     ntiles: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32),
                     emit_pos: wp.array(dtype=wp.int32), g_entry: wp.array2d(dtype=float),
                     g_means: wp.array2d(dtype=float), g_quats: wp.array2d(dtype=float),
                     g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float),
                     g_colors: wp.array2d(dtype=float), i: int):
    # Gaussian i's gradients; returns its viewmat part (rotation, translation)
    _prefetch_entries(ntiles, emit_start, emit_pos, g_entry, i)
    for k in range(3):
        g_means[i, k] = 0.0
        g_scales[i, k] = 0.0
        g_colors[i, k] = 0.0
    for k in range(4):
        g_quats[i, k] = 0.0
    g_opac[i] = 0.0
    nt = ntiles[i]
    if nt <= 0:
        return wp.mat33(0.0), wp.vec3(0.0)
    # this Gaussian's row gradient: the sum of its tile entries' gradients (no atomics)
    g_mx = float(0.0)
    g_my = float(0.0)
    gA = float(0.0)
    gB = float(0.0)
    gC = float(0.0)
    g_o = float(0.0)
    g_r = float(0.0)
    g_g = float(0.0)
    g_b = float(0.0)
    g_zr = float(0.0)
    k0 = emit_start[i]
    for k in range(k0, k0 + nt):
        e = emit_pos[k]
        g_mx += g_entry[e, 0]
        g_my += g_entry[e, 1]
        gA += g_entry[e, 2]
        gB += g_entry[e, 3]
        gC += g_entry[e, 4]
        g_o += g_entry[e, 5]
        g_r += g_entry[e, 6]
        g_g += g_entry[e, 7]
        g_b += g_entry[e, 8]
        g_zr += g_entry[e, 9]
    g_opac[i] = g_o
    g_colors[i, 0] = g_r
    g_colors[i, 1] = g_g
    g_colors[i, 2] = g_b
    # Recompute the forward intermediates (cheaper than storing them).
    m = wp.vec3(means[i, 0], means[i, 1], means[i, 2])
    p = wp.mul(Rv, m) + tv
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
    ga = -(A * A * gA + A * B * gB + B * B * gC)
    gb = -(2.0 * A * B * gA + (A * C + B * B) * gB + 2.0 * B * C * gC)
    gc = -(B * B * gA + B * C * gB + C * C * gC)
    gT0 = 2.0 * ga * T0 + gb * T1
    gT1 = gb * T0 + 2.0 * gc * T1
    gM0 = f0 * gT0
    gM1 = f1 * gT1
    gM2 = -(u * f0) * gT0 - (v * f1) * gT1
    g_inv_z = (wp.dot(gT0, T0) + wp.dot(gT1, T1)) * p[2]
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
    gz = g_zr - g_inv_z * inv_z * inv_z
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
    return gRv, gp


@wp.kernel
def _project_bwd(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                 view: wp.array2d(dtype=float), fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                 offset: int, count: int, n: int, proj: wp.array2d(dtype=float), ntiles: wp.array(dtype=wp.int32),
                 emit_start: wp.array(dtype=wp.int32), emit_pos: wp.array(dtype=wp.int32),
                 g_entry: wp.array2d(dtype=float), g_means: wp.array2d(dtype=float), g_quats: wp.array2d(dtype=float),
                 g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float), g_colors: wp.array2d(dtype=float),
                 g_view: wp.array2d(dtype=float)):
    # thread b = Gaussians [count b, + count); g_view[b] = the sum of their viewmat parts in index order
    # (rotation row-major, then translation). CUDA: count 1, one row per Gaussian; CPU: count BLOCK.
    b = wp.tid() + offset
    i0 = b * count
    sR = wp.mat33(0.0)
    st = wp.vec3(0.0)
    Rv = _view_rot(view)
    tv = wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    for i in range(i0, wp.min(i0 + count, n)):
        gR, gt = _project_bwd_one(means, quats, scales, Rv, tv, fx, fy, cx, cy, width, height, proj, ntiles,
                                  emit_start, emit_pos, g_entry, g_means, g_quats, g_scales, g_opac, g_colors, i)
        sR = sR + gR
        st = st + gt
    for r in range(3):
        for j in range(3):
            g_view[b, 3 * r + j] = sR[r, j]
        g_view[b, 9 + r] = st[r]


@wp.kernel
def _view_grad(parts: wp.array2d(dtype=float), n: int, block: int, g_view: wp.array2d(dtype=float)):
    # g_view [4, 4] = the n rows of parts summed: thread j < 9 -> rotation entry j, 9..11 -> translation, else 0;
    # summed in blocks of `block` rows (rows of single Gaussians: 256, pairwise-like accuracy for large N, float32
    # only; rows that are already the sums of 256 Gaussians: 1, the same sums)
    j = wp.tid()
    s = float(0.0)
    if j < 12:
        for b in range(0, n, block):
            sb = float(0.0)
            for i in range(b, wp.min(b + block, n)):
                sb += parts[i, j]
            s += sb
    if j < 9:
        g_view[j // 3, j % 3] = s
    elif j < 12:
        g_view[j - 9, 3] = s
    else:
        g_view[3, j - 12] = 0.0


def project_forward(means, quats, scales, opac, colors, view, intr, width, height, near, far, proj, radius, rect,
                    ntiles, pthr, device) -> None:
    n = means.shape[0]
    if n == 0:
        return
    fx, fy, cx, cy = intr
    count = BLOCK if device == "cpu" else 1
    inputs = [to_warp(means), to_warp(quats), to_warp(scales), to_warp(opac), to_warp(colors), to_warp(view),
              fx, fy, cx, cy, width, height, near, far, 0, count, n, to_warp(proj), to_warp(radius),
              to_warp(rect), to_warp(ntiles), to_warp(pthr)]
    kernel = _project_fwd_blocks if count > 1 else _project_fwd
    if device == "cpu" and CPU_PROJECT == "vector":
        kernel = _cpu.forward_blocks
    launch(kernel, (n + count - 1) // count, inputs, 14, device, work=n)


def project_backward(means, quats, scales, view, intr, width, height, proj, ntiles, emit_start, emit_pos, g_entry,
                     g_means, g_quats, g_scales, g_opac, g_colors, g_view, g_view_out, device) -> None:
    """g_view [N, 12] scratch for the viewmat parts (per Gaussian, or per BLOCK on the CPU), g_view_out [4, 4]
    their sum (None: not wanted, not summed)."""
    n = means.shape[0]
    if n == 0:
        return
    fx, fy, cx, cy = intr
    count = BLOCK if device == "cpu" else 1
    rows = (n + count - 1) // count
    inputs = [to_warp(means), to_warp(quats), to_warp(scales), to_warp(view), fx, fy, cx, cy, width, height, 0,
              count, n, to_warp(proj), to_warp(ntiles), to_warp(emit_start), to_warp(emit_pos), to_warp(g_entry),
              to_warp(g_means), to_warp(g_quats), to_warp(g_scales), to_warp(g_opac), to_warp(g_colors),
              to_warp(g_view)]
    launch(_cpu.backward_blocks if device == "cpu" and CPU_PROJECT == "vector" else _project_bwd, rows, inputs, 10,
           device, work=n)
    if g_view_out is not None:
        run(_view_grad, 16, [to_warp(g_view), rows, 256 // count, to_warp(g_view_out)], device)
