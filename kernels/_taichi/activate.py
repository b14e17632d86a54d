"""Taichi kernels of a mapping step's per-Gaussian activations: the rules of kernels/_warp/activate.py (read its
docstring), one loop iteration per Gaussian; contiguous float32 [N, 3] and [N] arrays."""

import taichi as ti

from .loss import _sign  # sign(0) = 0, as torch differentiates |x|

_f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_f2 = ti.types.ndarray(dtype=ti.f32, ndim=2)


@ti.kernel
def _forward(log_scales: _f2, logits: _f1, colors: _f2, n: ti.i32, scales: _f2, opac: _f1, colors01: _f2,
             absdev: _f1):
    for i in range(n):
        s0 = ti.exp(log_scales[i, 0])
        s1 = ti.exp(log_scales[i, 1])
        s2 = ti.exp(log_scales[i, 2])
        scales[i, 0] = s0
        scales[i, 1] = s1
        scales[i, 2] = s2
        t = s0 + s1 + s2
        absdev[i] = ti.abs(3.0 * s0 - t) + ti.abs(3.0 * s1 - t) + ti.abs(3.0 * s2 - t)
        opac[i] = 1.0 / (1.0 + ti.exp(-logits[i]))
        for k in ti.static(range(3)):
            colors01[i, k] = ti.math.clamp(colors[i, k], 0.0, 1.0)


@ti.kernel
def _backward(scales: _f2, opac: _f1, colors: _f2, g_scales: _f2, g_opac: _f1, g_colors: _f2, k_iso: ti.f32,
              n: ti.i32, d_log_scales: _f2, d_logits: _f1, d_colors: _f2):
    for i in range(n):
        s0 = scales[i, 0]
        s1 = scales[i, 1]
        s2 = scales[i, 2]
        t = s0 + s1 + s2
        q0 = _sign(3.0 * s0 - t)
        q1 = _sign(3.0 * s1 - t)
        q2 = _sign(3.0 * s2 - t)
        u = q0 + q1 + q2
        d_log_scales[i, 0] = (g_scales[i, 0] + k_iso * (3.0 * q0 - u)) * s0
        d_log_scales[i, 1] = (g_scales[i, 1] + k_iso * (3.0 * q1 - u)) * s1
        d_log_scales[i, 2] = (g_scales[i, 2] + k_iso * (3.0 * q2 - u)) * s2
        o = opac[i]
        d_logits[i] = g_opac[i] * (1.0 - o) * o
        for k in ti.static(range(3)):
            c = colors[i, k]
            g = 0.0
            if c >= 0.0 and c <= 1.0:
                g = g_colors[i, k]
            d_colors[i, k] = g


def forward(log_scales, logits, colors, scales, opac, colors01, absdev, device: str) -> None:
    n = logits.shape[0]
    if n:
        _forward(log_scales, logits, colors, n, scales, opac, colors01, absdev)
        if device == "cuda":
            ti.sync()


def backward(scales, opac, colors, g_scales, g_opac, g_colors, k_iso: float, d_log_scales, d_logits, d_colors,
             device: str) -> None:
    n = opac.shape[0]
    if n:
        _backward(scales, opac, colors, g_scales, g_opac, g_colors, float(k_iso), n, d_log_scales, d_logits,
                  d_colors)
        if device == "cuda":
            ti.sync()
