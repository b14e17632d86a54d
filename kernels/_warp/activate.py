"""Warp kernels of a mapping step's per-Gaussian activations (slam/dense/param_ops.py `activate`): one thread per
Gaussian on CUDA (and as the CPU's scalar peer); the CPU runs kernels/_warp/activate_cpu.py's vector blocks.

forward:  scales = exp(log_scales), opacities = sigmoid(logits), colors01 = clamp(colors, 0, 1), and per Gaussian
          absdev = sum_k |3 s_k - (s_0 + s_1 + s_2)| (3 times the row's absolute deviations from its mean; the
          isotropic-scale penalty mean |s - mean_row(s)| is sum(absdev) / (9 N)).
backward: d log_scales_k = (g_s_k + k_iso (3 sg_k - sum_j sg_j)) s_k with sg_k = sign(3 s_k - sum_j s_j),
          d logits = g_o o (1 - o), d colors_k = g_c_k where 0 <= colors_k <= 1 (as torch.clamp passes it), else 0.
All arrays float32 and contiguous (the CPU vector kernels read them as flat rows): [N, 3] and [N].
"""

from __future__ import annotations

import warp as wp

from . import activate_cpu as _cpu
from .arrays import to_warp
from .launch import launch
from .loss import _sign  # sign(0) = 0, as torch differentiates |x|

wp.set_module_options({"enable_backward": False})

# "vector": the CPU runs kernels/_warp/activate_cpu.py (BLOCK Gaussians per thread, vector code); "scalar": the
# kernels below, as on CUDA.
CPU_ACTIVATE = "vector"


@wp.kernel
def _forward(log_scales: wp.array2d(dtype=float), logits: wp.array(dtype=float), colors: wp.array2d(dtype=float),
             offset: int, scales: wp.array2d(dtype=float), opac: wp.array(dtype=float),
             colors01: wp.array2d(dtype=float), absdev: wp.array(dtype=float)):
    i = wp.tid() + offset
    s0 = wp.exp(log_scales[i, 0])
    s1 = wp.exp(log_scales[i, 1])
    s2 = wp.exp(log_scales[i, 2])
    scales[i, 0] = s0
    scales[i, 1] = s1
    scales[i, 2] = s2
    t = s0 + s1 + s2
    absdev[i] = wp.abs(3.0 * s0 - t) + wp.abs(3.0 * s1 - t) + wp.abs(3.0 * s2 - t)
    opac[i] = 1.0 / (1.0 + wp.exp(-logits[i]))
    for k in range(3):
        colors01[i, k] = wp.clamp(colors[i, k], 0.0, 1.0)


@wp.kernel
def _backward(scales: wp.array2d(dtype=float), opac: wp.array(dtype=float), colors: wp.array2d(dtype=float),
              g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float), g_colors: wp.array2d(dtype=float),
              k_iso: float, offset: int, d_log_scales: wp.array2d(dtype=float), d_logits: wp.array(dtype=float),
              d_colors: wp.array2d(dtype=float)):
    i = wp.tid() + offset
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
    for k in range(3):
        c = colors[i, k]
        g = float(0.0)
        if c >= 0.0 and c <= 1.0:
            g = g_colors[i, k]
        d_colors[i, k] = g


def _vector(device: str) -> bool:
    return device == "cpu" and CPU_ACTIVATE == "vector"


def forward(log_scales, logits, colors, scales, opac, colors01, absdev, device: str) -> None:
    n = logits.shape[0]
    arrays = [to_warp(t) for t in (log_scales, logits, colors)]
    outs = [to_warp(t) for t in (scales, opac, colors01, absdev)]
    if _vector(device):
        launch(_cpu.forward_blocks, (n + _cpu.BLOCK - 1) // _cpu.BLOCK, arrays + [0, n] + outs, 3, device, work=n)
    else:
        launch(_forward, n, arrays + [0] + outs, 3, device, work=n)


def backward(scales, opac, colors, g_scales, g_opac, g_colors, k_iso: float, d_log_scales, d_logits, d_colors,
             device: str) -> None:
    n = opac.shape[0]
    arrays = [to_warp(t) for t in (scales, opac, colors, g_scales, g_opac, g_colors)]
    outs = [to_warp(t) for t in (d_log_scales, d_logits, d_colors)]
    if _vector(device):
        launch(_cpu.backward_blocks, (n + _cpu.BLOCK - 1) // _cpu.BLOCK, arrays + [float(k_iso), 0, n] + outs, 7,
               device, work=n)
    else:
        launch(_backward, n, arrays + [float(k_iso), 0] + outs, 7, device, work=n)
