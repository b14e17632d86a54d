"""Taichi kernels of the EWA projection (one iteration per Gaussian) and its hand-written backward.

Same contract and algebra as kernels/_warp/project.py: rows in the kernels.raster.PACKED layout (zeros for culled
Gaussians), radius, tile rectangle, tile count (-1 for invalid inputs), exp() skip threshold; backward sums each
Gaussian's tile-entry gradients, then chains to means, quats, scales, opacity, colour and per-Gaussian [12]
viewmat slices, summed by `_view_grad`. Finiteness is tested on the bit pattern (Taichi compiles with fast math).
"""

import taichi as ti

from .launch import SPREAD, on_cpu

TILE = 16

_f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_f2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
_i1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_i2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


@ti.func
def _rotmat(w, x, y, z):
    return ti.Matrix([[1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
                      [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
                      [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)]], ti.f32)


@ti.func
def _finite(x):
    return (ti.bit_cast(x, ti.i32) & 0x7F800000) != 0x7F800000


@ti.func
def _view_rot(view: ti.template()):
    return ti.Matrix([[view[0, 0], view[0, 1], view[0, 2]], [view[1, 0], view[1, 1], view[1, 2]],
                      [view[2, 0], view[2, 1], view[2, 2]]], ti.f32)


@ti.kernel
def _project_fwd(means: _f2, quats: _f2, scales: _f2, opac: _f1, colors: _f2, view: _f2, fx: ti.f32, fy: ti.f32,
                 cx: ti.f32, cy: ti.f32, width: ti.i32, height: ti.i32, near: ti.f32, far: ti.f32, proj: _f2,
                 radius: _i1, rect: _i2, ntiles: _i1, pthr: _f1):
    for i in range(means.shape[0]):
        for k in ti.static(range(10)):
            proj[i, k] = 0.0
        for k in ti.static(range(4)):
            rect[i, k] = 0
        radius[i] = 0
        ntiles[i] = 0
        pthr[i] = 0.0
        ok = _finite(opac[i]) and opac[i] >= 0.0 and opac[i] <= 1.0
        qlen2 = 0.0
        for k in ti.static(range(3)):
            ok = ok and _finite(means[i, k]) and _finite(scales[i, k]) and _finite(colors[i, k])
        for k in ti.static(range(4)):
            ok = ok and _finite(quats[i, k])
            qlen2 += quats[i, k] * quats[i, k]
        z = 0.0
        if not ok or qlen2 < 1e-20:
            ntiles[i] = -1
            z = -1.0  # culls below
        Rv = _view_rot(view)
        p = Rv @ ti.Vector([means[i, 0], means[i, 1], means[i, 2]]) + ti.Vector([view[0, 3], view[1, 3], view[2, 3]])
        if z == 0.0:
            z = p[2]
        else:
            z = -1.0
        if z >= near and z <= far:
            inv_z = 1.0 / z
            lim_x = 0.15 * width / fx
            lim_y = 0.15 * height / fy
            u = ti.math.clamp(p[0] * inv_z, -(cx / fx + lim_x), (width - cx) / fx + lim_x)
            v = ti.math.clamp(p[1] * inv_z, -(cy / fy + lim_y), (height - cy) / fy + lim_y)
            q = ti.Vector([quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]])
            q = q / q.norm()
            N = Rv @ _rotmat(q[0], q[1], q[2], q[3])
            s = ti.Vector([scales[i, 0], scales[i, 1], scales[i, 2]])
            Mc = N @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]])
            m0 = ti.Vector([Mc[0, 0], Mc[0, 1], Mc[0, 2]])
            m1 = ti.Vector([Mc[1, 0], Mc[1, 1], Mc[1, 2]])
            m2 = ti.Vector([Mc[2, 0], Mc[2, 1], Mc[2, 2]])
            T0 = fx * inv_z * (m0 - u * m2)
            T1 = fy * inv_z * (m1 - v * m2)
            a = T0.dot(T0) + 0.3
            b = T0.dot(T1)
            c = T1.dot(T1) + 0.3
            det = a * c - b * b
            if det > 0.0:
                mx = fx * p[0] * inv_z + cx
                my = fy * p[1] * inv_z + cy
                mid = 0.5 * (a + c)
                r = ti.ceil(3.0 * ti.sqrt(mid + ti.sqrt(ti.max(mid * mid - det, 0.1))))
                ntx = ti.cast((width + TILE - 1) // TILE, ti.f32)
                nty = ti.cast((height + TILE - 1) // TILE, ti.f32)
                x0 = ti.math.clamp(ti.floor((mx - r) / TILE), 0.0, ntx)
                x1 = ti.math.clamp(ti.floor((mx + r) / TILE) + 1.0, 0.0, ntx)
                y0 = ti.math.clamp(ti.floor((my - r) / TILE), 0.0, nty)
                y1 = ti.math.clamp(ti.floor((my + r) / TILE) + 1.0, 0.0, nty)
                if x1 > x0 and y1 > y0:
                    # the tiles listed: the radius' rectangle cut to the box of the alpha >= 1/255 ellipse
                    # (widened as the compositing widens it; pixel centres at integers), which no composited
                    # pixel leaves
                    lo = -ti.log(255.0 * opac[i]) - 1e-5
                    tx0, tx1, ty0, ty1 = 0.0, 0.0, 0.0, 0.0
                    if lo < 0.0:
                        lgm = -1.01 * lo + 0.01
                        ex = ti.sqrt(2.0 * lgm * a)
                        ey = ti.sqrt(2.0 * lgm * c)
                        tx0 = ti.max(x0, ti.floor(ti.ceil(mx - ex) / TILE))
                        tx1 = ti.min(x1, ti.floor(ti.floor(mx + ex) / TILE) + 1.0)
                        ty0 = ti.max(y0, ti.floor(ti.ceil(my - ey) / TILE))
                        ty1 = ti.min(y1, ti.floor(ti.floor(my + ey) / TILE) + 1.0)
                    if not (tx1 > tx0 and ty1 > ty0):
                        tx0, tx1, ty0, ty1 = 0.0, 0.0, 0.0, 0.0
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
                    radius[i] = ti.cast(ti.min(r, 1073741824.0), ti.i32)
                    rect[i, 0] = ti.cast(tx0, ti.i32)
                    rect[i, 1] = ti.cast(ty0, ti.i32)
                    rect[i, 2] = ti.cast(tx1, ti.i32)
                    rect[i, 3] = ti.cast(ty1, ti.i32)
                    ntiles[i] = (rect[i, 2] - rect[i, 0]) * (rect[i, 3] - rect[i, 1])
                    pthr[i] = lo


@ti.kernel
def _project_bwd(means: _f2, quats: _f2, scales: _f2, view: _f2, fx: ti.f32, fy: ti.f32, cx: ti.f32, cy: ti.f32,
                 width: ti.i32, height: ti.i32, proj: _f2, ntiles: _i1, emit_start: _i1, emit_pos: _i1, g_entry: _f2,
                 g_means: _f2, g_quats: _f2, g_scales: _f2, g_opac: _f1, g_colors: _f2, g_view: _f2):
    # pass 1: each Gaussian's row gradient, the sum of its tile entries' (no atomics), into g_view[i, :10] as
    # scratch; a loop that only gathers keeps many of its cache misses in flight
    for i in range(means.shape[0]):
        nt = ntiles[i]
        if nt > 0:
            gs = ti.Vector([0.0] * 10)
            k0 = emit_start[i]
            for k in range(k0, k0 + nt):
                e = emit_pos[k]
                for j in ti.static(range(10)):
                    gs[j] += g_entry[e, j]
            for j in ti.static(range(10)):
                g_view[i, j] = gs[j]
    for i in range(means.shape[0]):
        nt = ntiles[i]
        gr = ti.Vector([0.0] * 10)
        if nt > 0:
            for j in ti.static(range(10)):
                gr[j] = g_view[i, j]
        for k in ti.static(range(3)):
            g_means[i, k] = 0.0
            g_scales[i, k] = 0.0
            g_colors[i, k] = 0.0
        for k in ti.static(range(4)):
            g_quats[i, k] = 0.0
        for k in ti.static(range(12)):
            g_view[i, k] = 0.0
        g_opac[i] = 0.0
        if nt > 0:
            g_opac[i] = gr[5]
            for j in ti.static(range(3)):
                g_colors[i, j] = gr[6 + j]
            Rv = _view_rot(view)
            m = ti.Vector([means[i, 0], means[i, 1], means[i, 2]])
            p = Rv @ m + ti.Vector([view[0, 3], view[1, 3], view[2, 3]])
            inv_z = 1.0 / p[2]
            lim_x = 0.15 * width / fx
            lim_y = 0.15 * height / fy
            ru = p[0] * inv_z
            rv = p[1] * inv_z
            u = ti.math.clamp(ru, -(cx / fx + lim_x), (width - cx) / fx + lim_x)
            v = ti.math.clamp(rv, -(cy / fy + lim_y), (height - cy) / fy + lim_y)
            q = ti.Vector([quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]])
            qlen = q.norm()
            w, x, y, z = q[0] / qlen, q[1] / qlen, q[2] / qlen, q[3] / qlen
            Rq = _rotmat(w, x, y, z)
            N = Rv @ Rq
            s = ti.Vector([scales[i, 0], scales[i, 1], scales[i, 2]])
            S = ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]])
            Mc = N @ S
            m0 = ti.Vector([Mc[0, 0], Mc[0, 1], Mc[0, 2]])
            m1 = ti.Vector([Mc[1, 0], Mc[1, 1], Mc[1, 2]])
            m2 = ti.Vector([Mc[2, 0], Mc[2, 1], Mc[2, 2]])
            f0 = fx * inv_z
            f1 = fy * inv_z
            T0 = f0 * (m0 - u * m2)
            T1 = f1 * (m1 - v * m2)
            A, B, C = proj[i, 2], proj[i, 3], proj[i, 4]
            gA, gB, gC = gr[2], gr[3], gr[4]
            ga = -(A * A * gA + A * B * gB + B * B * gC)
            gb = -(2.0 * A * B * gA + (A * C + B * B) * gB + 2.0 * B * C * gC)
            gc = -(B * B * gA + B * C * gB + C * C * gC)
            gT0 = 2.0 * ga * T0 + gb * T1
            gT1 = gb * T0 + 2.0 * gc * T1
            gM0 = f0 * gT0
            gM1 = f1 * gT1
            gM2 = -(u * f0) * gT0 - (v * f1) * gT1
            g_inv_z = (gT0.dot(T0) + gT1.dot(T1)) * p[2]
            g_mx, g_my = gr[0], gr[1]
            gx = g_mx * f0
            gy = g_my * f1
            g_inv_z += g_mx * fx * p[0] + g_my * fy * p[1]
            if ru == u:  # the field-of-view clamp passes gradients only where it is not active
                gu = -f0 * gT0.dot(m2)
                gx += gu * inv_z
                g_inv_z += gu * p[0]
            if rv == v:
                gv = -f1 * gT1.dot(m2)
                gy += gv * inv_z
                g_inv_z += gv * p[1]
            gz = gr[9] - g_inv_z * inv_z * inv_z
            gp = ti.Vector([gx, gy, gz])
            gMc = ti.Matrix([[gM0[0], gM0[1], gM0[2]], [gM1[0], gM1[1], gM1[2]], [gM2[0], gM2[1], gM2[2]]])
            gN = gMc @ S
            for j in ti.static(range(3)):
                g_scales[i, j] = gMc[0, j] * N[0, j] + gMc[1, j] * N[1, j] + gMc[2, j] * N[2, j]
            G = Rv.transpose() @ gN  # dL/dRq
            gw = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
            gxq = 2.0 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2.0 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                         + w * G[2, 1] - 2.0 * x * G[2, 2])
            gyq = 2.0 * (-2.0 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                         + z * G[2, 1] - 2.0 * y * G[2, 2])
            gzq = 2.0 * (-2.0 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2.0 * z * G[1, 1]
                         + y * G[1, 2] + x * G[2, 0] + y * G[2, 1])
            dot = w * gw + x * gxq + y * gyq + z * gzq
            g_quats[i, 0] = (gw - w * dot) / qlen
            g_quats[i, 1] = (gxq - x * dot) / qlen
            g_quats[i, 2] = (gyq - y * dot) / qlen
            g_quats[i, 3] = (gzq - z * dot) / qlen
            gm = Rv.transpose() @ gp
            for j in ti.static(range(3)):
                g_means[i, j] = gm[j]
            gRv = gN @ Rq.transpose() + gp.outer_product(m)
            for r in ti.static(range(3)):
                for j in ti.static(range(3)):
                    g_view[i, 3 * r + j] = gRv[r, j]
                g_view[i, 9 + r] = gp[r]


@ti.kernel
def _view_grad(parts: _f2, n: ti.i32, g_view: _f2):
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: the 12 sums on all cores (kernels/_taichi/launch.py)
    for it in range(16 * sp):  # g_view [4, 4]: j < 9 rotation entry j, 9..11 translation, else 0
        if it % sp != 0:
            continue
        j = it // sp
        s = 0.0
        if j < 12:  # summed in blocks of 256 (pairwise-like accuracy for large N, float32 only)
            for b in range((n + 255) // 256):
                sb = 0.0
                for i in range(b * 256, ti.min(b * 256 + 256, n)):
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
    if means.shape[0] == 0:
        return
    fx, fy, cx, cy = intr
    _project_fwd(means, quats, scales, opac, colors, view, fx, fy, cx, cy, width, height, near, far, proj, radius, rect,
                 ntiles, pthr)
    if device == "cuda":
        ti.sync()


def project_backward(means, quats, scales, view, intr, width, height, proj, ntiles, emit_start, emit_pos, g_entry,
                     g_means, g_quats, g_scales, g_opac, g_colors, g_view, g_view_out, device) -> None:
    """g_view [N, 12] per-Gaussian viewmat parts (scratch), g_view_out [4, 4] their sum (None: not wanted)."""
    n = means.shape[0]
    if n == 0:
        return
    fx, fy, cx, cy = intr
    _project_bwd(means, quats, scales, view, fx, fy, cx, cy, width, height, proj, ntiles, emit_start, emit_pos,
                 g_entry, g_means, g_quats, g_scales, g_opac, g_colors, g_view)
    if g_view_out is not None:
        _view_grad(g_view, n, g_view_out)
    if device == "cuda":
        ti.sync()
