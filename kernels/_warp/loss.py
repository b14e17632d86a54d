"""Warp kernels of the mapping loss (GRAND-SLAM eq. 3, slam.dense.render.rgbd_loss's rules) in two passes over pixel rows.

Pass 1 writes the per-pixel colour error e_c = mean_c |I^ - I|, depth error e_d = |D^ - D| [D > 0] and the alpha
mask m0 = alpha^p (1 when p = 0). The caller takes the medians of e_c, e_d over the mask (the inlier rule), then
pass 2 applies the inlier thresholds and writes the final mask m and each row's sums of m and
m (lambda e_c + (1 - lambda) e_d). The backward writes dL/dI^ = ((s m) lambda) / 3 sign(I^ - I) and
dL/dD^ = ((s m) (1 - lambda)) [D > 0] sign(D^ - D) for s = upstream / weight, in the order torch's autograd
rounds them for slam.dense.render.rgbd_loss (the optimiser downstream amplifies last-bit differences).
One thread per image row, no atomics; flat [H * W (* 3)] arrays.
"""

from __future__ import annotations

import warp as wp

from . import loss_cpu as _cpu
from .arrays import to_warp
from .launch import launch

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

# "native": the CPU runs kernels/_warp/loss_cpu.py (flat row loops over contiguous arrays, vector code, bitwise
# equal outputs); "scalar": the kernels below, as on CUDA (perf's scalar peer).
CPU_LOSS = "native"


def _pick(kernel, native, device: str, *tensors):
    if device == "cpu" and CPU_LOSS == "native" and all(t.is_contiguous() for t in tensors):
        return native
    return kernel


@wp.func
def _sign(x: float):
    s = float(0.0)
    if x > 0.0:
        s = 1.0
    elif x < 0.0:
        s = -1.0
    return s


@wp.kernel
def _errors(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
            depth: wp.array(dtype=float), alpha: wp.array(dtype=float), width: int, power: float, offset: int,
            e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0: wp.array(dtype=float)):
    y = wp.tid() + offset
    for x in range(width):
        q = y * width + x
        e_c[q] = (wp.abs(r_c[3 * q] - color[3 * q]) + wp.abs(r_c[3 * q + 1] - color[3 * q + 1])
                  + wp.abs(r_c[3 * q + 2] - color[3 * q + 2])) / 3.0
        ed = float(0.0)
        if depth[q] > 0.0:
            ed = wp.abs(r_d[q] - depth[q])
        e_d[q] = ed
        m = float(1.0)
        if power > 0.0:
            m = wp.pow(wp.clamp(alpha[q], 0.0, 1.0), power)
        m0[q] = m


@wp.kernel
def _masked_sums(e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0: wp.array(dtype=float), width: int,
                 lam: float, lam_d: float, thr_c: float, thr_d: float, offset: int, row_sums: wp.array2d(dtype=float),
                 mask: wp.array(dtype=float)):
    y = wp.tid() + offset
    sw = float(0.0)
    sl = float(0.0)
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


@wp.kernel
def _grads(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
           depth: wp.array(dtype=float), mask: wp.array(dtype=float), width: int, s: float, lam: float, lam_d: float,
           offset: int, g_c: wp.array(dtype=float), g_d: wp.array(dtype=float)):
    y = wp.tid() + offset
    for x in range(width):
        q = y * width + x
        sm = s * mask[q]
        kc = (sm * lam) / 3.0
        for c in range(3):
            g_c[3 * q + c] = kc * _sign(r_c[3 * q + c] - color[3 * q + c])
        gd = float(0.0)
        if depth[q] > 0.0:
            gd = (sm * lam_d) * _sign(r_d[q] - depth[q])
        g_d[q] = gd


def errors(r_c, color, r_d, depth, alpha, power: float, e_c, e_d, m0, device: str) -> None:
    h, w = depth.shape
    ins = [t.reshape(-1) for t in (r_c, color, r_d, depth, alpha)]
    inputs = [to_warp(t) for t in ins] + [w, float(power), 0] + [to_warp(t) for t in (e_c, e_d, m0)]
    kernel = _pick(_errors, _cpu.errors, device, *ins, e_c, e_d, m0)
    launch(kernel, h, inputs, 7, device, work=h * w // 16)  # 320x240: one thread


def masked_sums(e_c, e_d, m0, width: int, lam: float, lam_d: float, thr_c: float, thr_d: float, row_sums, mask,
                device: str) -> None:
    h = row_sums.shape[0]
    inputs = [to_warp(t) for t in (e_c, e_d, m0)] + [width, float(lam), float(lam_d), float(thr_c), float(thr_d), 0,
                                                     to_warp(row_sums), to_warp(mask)]
    kernel = _pick(_masked_sums, _cpu.masked_sums, device, e_c, e_d, m0, mask)
    launch(kernel, h, inputs, 8, device, work=h * width // 16)


def grads(r_c, color, r_d, depth, mask, s: float, lam: float, lam_d: float, g_c, g_d, device: str) -> None:
    h, w = depth.shape
    ins = [t.reshape(-1) for t in (r_c, color, r_d, depth)]
    inputs = [to_warp(t) for t in ins] + [to_warp(mask), w, float(s), float(lam), float(lam_d), 0, to_warp(g_c),
                                          to_warp(g_d)]
    kernel = _pick(_grads, _cpu.grads, device, *ins, mask, g_c, g_d)
    launch(kernel, h, inputs, 9, device, work=h * w // 16)
