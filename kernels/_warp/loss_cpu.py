"""CPU kernels of the mapping loss (kernels/_warp/loss.py has the rules), as native code over plain pointers.

Warp's CPU code generator indexes every array through its runtime strides and emits scalar code, so the three
passes of eq. 3 over a 320x240 frame cost ~0.45 / 0.3 / 0.6 ms on one core (the loss runs on one thread there:
too little work to hand to another): ~1.4 ms of a ~31 ms mapping iteration. Here each image row is a flat loop
the compiler vectorises (the colour and depth errors, the inlier mask, the gradients with their signs); the
alpha mask's power stays a call of the same powf per pixel, and each row's two sums are added in pixel order as
there. The arithmetic is the scalar kernels' expression for expression, compiled without multiply-add
contraction, so every output is bitwise equal to theirs (tests/test_mapping_loss.py), which keeps the gradients
rounded as torch's autograd rounds the twin slam.dense.render.rgbd_loss. The flat arrays must be contiguous
(loss.py falls back to the scalar kernels otherwise). CPU only: CUDA runs loss.py's kernels.
"""

from __future__ import annotations

import warp as wp

CPU_ONLY = True  # perf/gpu_codegen.py does not build this module for CUDA

# no FMA contraction: m (lam e_c + lam_d e_d) and the gradient products round as in the scalar kernels
wp.set_module_options({"enable_backward": False, "max_unroll": 0,
                       "cpu_compiler_flags": "-march=native -ffp-contract=off"})

# row y of the rendered and the observed colour and depth (both kernels that read them)
_RENDERED = r"""
    const int q0 = y * width;
    const float* __restrict__ rc = (const float*)r_c.data + 3 * q0;
    const float* __restrict__ co = (const float*)color.data + 3 * q0;
    const float* __restrict__ rd = (const float*)r_d.data + q0;
    const float* __restrict__ de = (const float*)depth.data + q0;
"""

_ERRORS = _RENDERED + r"""
    const float* __restrict__ al = (const float*)alpha.data + q0;
    float* __restrict__ ec = (float*)e_c.data + q0;
    float* __restrict__ ed = (float*)e_d.data + q0;
    float* __restrict__ m0 = (float*)m0_.data + q0;
    for (int x = 0; x < width; ++x) {
        ec[x] = (fabsf(rc[3 * x] - co[3 * x]) + fabsf(rc[3 * x + 1] - co[3 * x + 1])
                 + fabsf(rc[3 * x + 2] - co[3 * x + 2])) / 3.0f;
        const float d = de[x];
        const float e = fabsf(rd[x] - d);
        ed[x] = d > 0.0f ? e : 0.0f;
    }
    if (power > 0.0f) {
        for (int x = 0; x < width; ++x) {
            m0[x] = wp::pow(wp::clamp(al[x], 0.0f, 1.0f), power);  // Warp's own, as the scalar kernel calls them
        }
    } else {
        for (int x = 0; x < width; ++x) m0[x] = 1.0f;
    }
"""

_MASKED_SUMS = r"""
    const int q0 = y * width;
    const float* __restrict__ ec = (const float*)e_c.data + q0;
    const float* __restrict__ ed = (const float*)e_d.data + q0;
    const float* __restrict__ m0 = (const float*)m0_.data + q0;
    float* __restrict__ mk = (float*)mask.data + q0;
    for (int x = 0; x < width; ++x) {
        const bool out = (ec[x] > thr_c) | (ed[x] > thr_d);  // false for NaN, as the scalar kernel's test
        mk[x] = out ? 0.0f : m0[x];
    }
    float sw = 0.0f, sl = 0.0f;
    for (int x = 0; x < width; ++x) {  // in pixel order: the scalar kernel's rounding
        const float m = mk[x];
        sw += m;
        const float t1 = lam * ec[x];
        const float t2 = lam_d * ed[x];
        sl += m * (t1 + t2);
    }
    float* rs = (float*)((char*)row_sums.data + (size_t)y * row_sums.strides[0]);
    const size_t rj = row_sums.strides[1] / sizeof(float);
    rs[0] = sw;
    rs[rj] = sl;
"""

_GRADS = _RENDERED + r"""
    const float* __restrict__ mk = (const float*)mask.data + q0;
    float* __restrict__ gc = (float*)g_c.data + 3 * q0;
    float* __restrict__ gd = (float*)g_d.data + q0;
    auto sgn = [](float v) -> float { return v > 0.0f ? 1.0f : (v < 0.0f ? -1.0f : 0.0f); };
    for (int x = 0; x < width; ++x) {
        const float sm = s * mk[x];
        const float t = sm * lam;
        const float kc = t / 3.0f;
        gc[3 * x] = kc * sgn(rc[3 * x] - co[3 * x]);
        gc[3 * x + 1] = kc * sgn(rc[3 * x + 1] - co[3 * x + 1]);
        gc[3 * x + 2] = kc * sgn(rc[3 * x + 2] - co[3 * x + 2]);
        const float kd = sm * lam_d;
        const float g = kd * sgn(rd[x] - de[x]);
        gd[x] = de[x] > 0.0f ? g : 0.0f;
    }
"""


@wp.func_native(_ERRORS)
def _errors_row(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
                depth: wp.array(dtype=float), alpha: wp.array(dtype=float), width: int, power: float, y: int,
                e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0_: wp.array(dtype=float)):
    ...


@wp.func_native(_MASKED_SUMS)
def _masked_sums_row(e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0_: wp.array(dtype=float), width: int,
                     lam: float, lam_d: float, thr_c: float, thr_d: float, y: int,
                     row_sums: wp.array2d(dtype=float), mask: wp.array(dtype=float)):
    ...


@wp.func_native(_GRADS)
def _grads_row(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
               depth: wp.array(dtype=float), mask: wp.array(dtype=float), width: int, s: float, lam: float,
               lam_d: float, y: int, g_c: wp.array(dtype=float), g_d: wp.array(dtype=float)):
    ...


# The same argument lists as kernels/_warp/loss.py's _errors, _masked_sums and _grads (its launches take either).
@wp.kernel
def errors(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
           depth: wp.array(dtype=float), alpha: wp.array(dtype=float), width: int, power: float, offset: int,
           e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0: wp.array(dtype=float)):
    _errors_row(r_c, color, r_d, depth, alpha, width, power, wp.tid() + offset, e_c, e_d, m0)


@wp.kernel
def masked_sums(e_c: wp.array(dtype=float), e_d: wp.array(dtype=float), m0: wp.array(dtype=float), width: int,
                lam: float, lam_d: float, thr_c: float, thr_d: float, offset: int,
                row_sums: wp.array2d(dtype=float), mask: wp.array(dtype=float)):
    _masked_sums_row(e_c, e_d, m0, width, lam, lam_d, thr_c, thr_d, wp.tid() + offset, row_sums, mask)


@wp.kernel
def grads(r_c: wp.array(dtype=float), color: wp.array(dtype=float), r_d: wp.array(dtype=float),
          depth: wp.array(dtype=float), mask: wp.array(dtype=float), width: int, s: float, lam: float, lam_d: float,
          offset: int, g_c: wp.array(dtype=float), g_d: wp.array(dtype=float)):
    _grads_row(r_c, color, r_d, depth, mask, width, s, lam, lam_d, wp.tid() + offset, g_c, g_d)
