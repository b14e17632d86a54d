"""CPU kernels of the per-Gaussian activations (kernels/_warp/activate.py has the rules), written for the CPU's
vector units: one kernel thread takes BLOCK consecutive Gaussians and runs flat loops over their [3 BLOCK] and
[BLOCK] entries that the compiler vectorises, with a polynomial exp (no library call in the loop). Torch's own
operations for the same work (exp, sigmoid, clamp and the isotropic penalty's row sums and signs, forward and
backward) cost ~2-3 ms per mapping step at 60k Gaussians on one core: [N, 3] reductions are slow there.
Same values as the scalar kernels up to float32 rounding (exp's relative error 1.2e-7 on the whole float range).
The arrays must be contiguous (activate.py's callers pass them so).
"""

from __future__ import annotations

import warp as wp

CPU_ONLY = True  # perf/gpu_codegen.py does not build this module for CUDA

wp.set_module_options({"enable_backward": False, "max_unroll": 0, "cpu_compiler_flags": (
    "-march=native -ffp-contract=fast -mllvm=-inline-threshold=9000")})

BLOCK = 4096  # Gaussians per kernel thread
_BLOCK = wp.constant(BLOCK)

_COMMON = r"""
    const int i_end = (i0 + count < n ? i0 + count : n);
    auto fexp = [](float x) -> float {
        // exp(x), x clamped to [-87, 88] (float32's normal range): x = n ln2 + r, |r| <= ln2 / 2, exp(r) =
        // 1 + r + r^2 P(r) with Cephes' expf coefficients, 2^n from the exponent bits
        x = x < 88.0f ? x : 88.0f;
        x = x > -87.0f ? x : -87.0f;
        float m = floorf(x * 1.44269504088896341f + 0.5f);
        float r = x - m * 0.693145751953125f;
        r = r - m * 1.42860682030941723e-06f;
        const float r2 = r * r;
        const float pa = 5.0000001201e-1f + 1.6666665459e-1f * r;
        const float pb = 4.1665795894e-2f + 8.3334519073e-3f * r;
        const float pc = 1.3981999507e-3f + 1.9875691500e-4f * r;
        const float p = (1.0f + r) + r2 * (pa + r2 * (pb + r2 * pc));
        int bits = ((int)m + 127) << 23;
        float scale;
        __builtin_memcpy(&scale, &bits, 4);
        return p * scale;
    };
    auto sgn = [](float x) -> float { return x > 0.0f ? 1.0f : (x < 0.0f ? -1.0f : 0.0f); };
"""

_FORWARD = _COMMON + r"""
    if (i0 >= i_end) return;
    const float* ls = (const float*)log_scales.data;
    const float* lo = (const float*)logits.data;
    const float* col = (const float*)colors.data;
    float* s = (float*)scales.data;
    float* o = (float*)opac.data;
    float* c = (float*)colors01.data;
    float* ad = (float*)absdev.data;
    for (int j = 3 * i0; j < 3 * i_end; ++j) s[j] = fexp(ls[j]);
    for (int j = 3 * i0; j < 3 * i_end; ++j) {
        float x = col[j];
        x = x > 0.0f ? x : 0.0f;
        c[j] = x < 1.0f ? x : 1.0f;
    }
    for (int i = i0; i < i_end; ++i) o[i] = 1.0f / (1.0f + fexp(-lo[i]));
    for (int i = i0; i < i_end; ++i) {
        const float s0 = s[3 * i], s1 = s[3 * i + 1], s2 = s[3 * i + 2];
        const float t = s0 + s1 + s2;
        ad[i] = fabsf(3.0f * s0 - t) + fabsf(3.0f * s1 - t) + fabsf(3.0f * s2 - t);
    }
"""

_BACKWARD = _COMMON + r"""
    if (i0 >= i_end) return;
    const float* s = (const float*)scales.data;
    const float* o = (const float*)opac.data;
    const float* col = (const float*)colors.data;
    const float* gs = (const float*)g_scales.data;
    const float* go = (const float*)g_opac.data;
    const float* gc = (const float*)g_colors.data;
    float* dls = (float*)d_log_scales.data;
    float* dlo = (float*)d_logits.data;
    float* dc = (float*)d_colors.data;
    for (int i = i0; i < i_end; ++i) {
        const float s0 = s[3 * i], s1 = s[3 * i + 1], s2 = s[3 * i + 2];
        const float t = s0 + s1 + s2;
        const float q0 = sgn(3.0f * s0 - t), q1 = sgn(3.0f * s1 - t), q2 = sgn(3.0f * s2 - t);
        const float u = q0 + q1 + q2;
        dls[3 * i] = (gs[3 * i] + k_iso * (3.0f * q0 - u)) * s0;
        dls[3 * i + 1] = (gs[3 * i + 1] + k_iso * (3.0f * q1 - u)) * s1;
        dls[3 * i + 2] = (gs[3 * i + 2] + k_iso * (3.0f * q2 - u)) * s2;
    }
    for (int i = i0; i < i_end; ++i) dlo[i] = go[i] * (1.0f - o[i]) * o[i];
    for (int j = 3 * i0; j < 3 * i_end; ++j) dc[j] = (col[j] >= 0.0f && col[j] <= 1.0f) ? gc[j] : 0.0f;
"""


@wp.func_native(_FORWARD)
def _fwd_block(log_scales: wp.array2d(dtype=float), logits: wp.array(dtype=float), colors: wp.array2d(dtype=float),
               i0: int, count: int, n: int, scales: wp.array2d(dtype=float), opac: wp.array(dtype=float),
               colors01: wp.array2d(dtype=float), absdev: wp.array(dtype=float)):
    ...


@wp.func_native(_BACKWARD)
def _bwd_block(scales: wp.array2d(dtype=float), opac: wp.array(dtype=float), colors: wp.array2d(dtype=float),
               g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float), g_colors: wp.array2d(dtype=float),
               k_iso: float, i0: int, count: int, n: int, d_log_scales: wp.array2d(dtype=float),
               d_logits: wp.array(dtype=float), d_colors: wp.array2d(dtype=float)):
    ...


# thread = Gaussians [BLOCK (tid + offset), + BLOCK) of n
@wp.kernel
def forward_blocks(log_scales: wp.array2d(dtype=float), logits: wp.array(dtype=float),
                   colors: wp.array2d(dtype=float), offset: int, n: int, scales: wp.array2d(dtype=float),
                   opac: wp.array(dtype=float), colors01: wp.array2d(dtype=float), absdev: wp.array(dtype=float)):
    _fwd_block(log_scales, logits, colors, (wp.tid() + offset) * _BLOCK, _BLOCK, n, scales, opac, colors01, absdev)


@wp.kernel
def backward_blocks(scales: wp.array2d(dtype=float), opac: wp.array(dtype=float), colors: wp.array2d(dtype=float),
                    g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float),
                    g_colors: wp.array2d(dtype=float), k_iso: float, offset: int, n: int,
                    d_log_scales: wp.array2d(dtype=float), d_logits: wp.array(dtype=float),
                    d_colors: wp.array2d(dtype=float)):
    _bwd_block(scales, opac, colors, g_scales, g_opac, g_colors, k_iso, (wp.tid() + offset) * _BLOCK, _BLOCK, n,
               d_log_scales, d_logits, d_colors)
