"""Taichi kernels of the mapping loss: the same passes as kernels/_warp/loss.py (read its docstring), one
iteration per image row, flat arrays."""

import taichi as ti

from .launch import SPREAD, on_cpu

_f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_f2 = ti.types.ndarray(dtype=ti.f32, ndim=2)


@ti.func
def _sign(x):
    s = 0.0
    if x > 0.0:
        s = 1.0
    elif x < 0.0:
        s = -1.0
    return s


@ti.kernel
def _errors(r_c: _f1, color: _f1, r_d: _f1, depth: _f1, alpha: _f1, height: ti.i32, width: ti.i32, power: ti.f32,
            e_c: _f1, e_d: _f1, m0: _f1):
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: rows spread over the cores (kernels/_taichi/launch.py)
    for it in range(height * sp):
        if it % sp != 0:
            continue
        y = it // sp
        for x in range(width):
            q = y * width + x
            e_c[q] = (ti.abs(r_c[3 * q] - color[3 * q]) + ti.abs(r_c[3 * q + 1] - color[3 * q + 1])
                      + ti.abs(r_c[3 * q + 2] - color[3 * q + 2])) / 3.0
            ed = 0.0
            if depth[q] > 0.0:
                ed = ti.abs(r_d[q] - depth[q])
            e_d[q] = ed
            m = 1.0
            if power > 0.0:
                m = ti.pow(ti.math.clamp(alpha[q], 0.0, 1.0), power)
            m0[q] = m


@ti.kernel
def _masked_sums(e_c: _f1, e_d: _f1, m0: _f1, height: ti.i32, width: ti.i32, lam: ti.f32, lam_d: ti.f32,
                 thr_c: ti.f32, thr_d: ti.f32, row_sums: _f2, mask: _f1):
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: rows spread over the cores (kernels/_taichi/launch.py)
    for it in range(height * sp):
        if it % sp != 0:
            continue
        y = it // sp
        sw = 0.0
        sl = 0.0
        for x in range(width):
            q = y * width + x
            m = m0[q]
            if e_c[q] > thr_c or e_d[q] > thr_d:
                m = 0.0
            mask[q] = m
            sw += m
            sl += m * (lam * e_c[q] + lam_d * e_d[q])
        row_sums[y, 0] = sw
        row_sums[y, 1] = sl


@ti.kernel
def _grads(r_c: _f1, color: _f1, r_d: _f1, depth: _f1, mask: _f1, height: ti.i32, width: ti.i32, s: ti.f32,
           lam: ti.f32, lam_d: ti.f32, g_c: _f1, g_d: _f1):
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: rows spread over the cores (kernels/_taichi/launch.py)
    for it in range(height * sp):
        if it % sp != 0:
            continue
        y = it // sp
        for x in range(width):
            q = y * width + x
            sm = s * mask[q]
            kc = (sm * lam) / 3.0
            for c in ti.static(range(3)):
                g_c[3 * q + c] = kc * _sign(r_c[3 * q + c] - color[3 * q + c])
            gd = 0.0
            if depth[q] > 0.0:
                gd = (sm * lam_d) * _sign(r_d[q] - depth[q])
            g_d[q] = gd


def errors(r_c, color, r_d, depth, alpha, power: float, e_c, e_d, m0, device: str) -> None:
    h, w = depth.shape
    _errors(*(t.reshape(-1) for t in (r_c, color, r_d, depth, alpha)), h, w, float(power), e_c, e_d, m0)
    if device == "cuda":
        ti.sync()


def masked_sums(e_c, e_d, m0, width: int, lam: float, lam_d: float, thr_c: float, thr_d: float, row_sums, mask,
                device: str) -> None:
    _masked_sums(e_c, e_d, m0, row_sums.shape[0], width, float(lam), float(lam_d), float(thr_c), float(thr_d),
                 row_sums, mask)
    if device == "cuda":
        ti.sync()


def grads(r_c, color, r_d, depth, mask, s: float, lam: float, lam_d: float, g_c, g_d, device: str) -> None:
    h, w = depth.shape
    _grads(*(t.reshape(-1) for t in (r_c, color, r_d, depth)), mask, h, w, float(s), float(lam), float(lam_d), g_c,
           g_d)
    if device == "cuda":
        ti.sync()
