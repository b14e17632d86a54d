"""Warp CPU/CUDA kernels of the ICP normal equations: one pass over the source points sums the robust
point-to-plane (and, optionally, photometric) Gauss-Newton terms, with projective association fused in or from
an index array. Association, normals and the hash grid are in kernels/_warp/icp.py, which re-exports
`reduce_point_to_plane` as part of the backend module `icp`."""

from __future__ import annotations

import torch
import warp as wp

from ..icp import N_SLOTS, n_blocks, reduce_terms
from .icp import _arr, _mat, _project_assoc, _sync, _xform
from .launch import launch as _launch

wp.set_module_options({"enable_backward": False})


@wp.func
def _bilinear1(img: wp.array2d(dtype=wp.float32), u: float, v: float):
    x0 = int(wp.floor(u))
    y0 = int(wp.floor(v))
    a = u - float(x0)
    b = v - float(y0)
    return (img[y0, x0] * (1.0 - a) * (1.0 - b) + img[y0, x0 + 1] * a * (1.0 - b)
            + img[y0 + 1, x0] * (1.0 - a) * b + img[y0 + 1, x0 + 1] * a * b)


@wp.func
def _robust_w(r: float, kind: int, k: float):
    a = wp.abs(r)
    if kind == 1:
        if a <= k:
            return 1.0
        return k / a
    if kind == 2:
        if a <= k:
            t = 1.0 - (r / k) * (r / k)
            return t * t
        return 0.0
    return 1.0


vec33f = wp.types.vector(length=33, dtype=wp.float32)
vec33d = wp.types.vector(length=33, dtype=wp.float64)
SUB = 64  # points summed in float32 before each float64 flush


@wp.func
def _contrib(J: wp.spatial_vectorf, w: float, r: float, e0: float, e1: float, e2: float, e3: float, e4: float,
             e5: float):
    # Packed per-point terms: [0:21] upper triangle of w J J^T (row-major), [21:27] w r J, [27:33] the extras.
    a0 = J[0]
    a1 = J[1]
    a2 = J[2]
    a3 = J[3]
    a4 = J[4]
    a5 = J[5]
    b0 = w * a0
    b1 = w * a1
    b2 = w * a2
    b3 = w * a3
    b4 = w * a4
    b5 = w * a5
    return vec33f(b0 * a0, b0 * a1, b0 * a2, b0 * a3, b0 * a4, b0 * a5, b1 * a1, b1 * a2, b1 * a3, b1 * a4, b1 * a5,
                  b2 * a2, b2 * a3, b2 * a4, b2 * a5, b3 * a3, b3 * a4, b3 * a5, b4 * a4, b4 * a5, b5 * a5,
                  b0 * r, b1 * r, b2 * r, b3 * r, b4 * r, b5 * r, e0, e1, e2, e3, e4, e5)


def _make_reduce(projective: bool, photo: bool):
    """The reduction kernel specialised at compile time (wp.static) for the association mode and the photometric
    term. Measured choices for Warp's CPU code: no local is assigned under a run-time branch (Warp copies those;
    unmatched points leave the loop body with `continue`), and each run of SUB points is summed in float32 over the
    upper triangle only before a float64 flush (1.8x faster than a float64 6x6 outer product per point; a
    float32 6x6 outer product or 8-wide row vectors were 1.3x slower)."""

    # GPU: n_blocks(n, "cuda") threads (up to 16384), each summing every 16384-th point (coalesced loads), in
    # REDUCE_GPU_BLOCK = 128 per block; 146-160 registers (the float32 and float64 33-wide sums) -> 25 % occupancy;
    # no stack frame, no atomics: one [48] float64 row per thread, summed by torch.
    @wp.kernel(module="unique", enable_backward=False)
    def _reduce(src: wp.array(dtype=wp.vec3), T: wp.mat44, tp: wp.array(dtype=wp.vec3),
                tn: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.int32), kind: int, k: float,
                s_int: wp.array(dtype=wp.float32), t_int: wp.array2d(dtype=wp.float32),
                t_gu: wp.array2d(dtype=wp.float32), t_gv: wp.array2d(dtype=wp.float32),
                fx: float, fy: float, cx: float, cy: float, lam: float,
                sn: wp.array(dtype=wp.vec3), th: int, tw: int, max_d: float, cos_min: float,
                block0: int, start_stride: int, item_stride: int, count: int, out: wp.array2d(dtype=wp.float64)):
        b = wp.tid() + block0
        n_pts = src.shape[0]
        acc = vec33d()
        for s in range((count + SUB - 1) // SUB):
            part = vec33f()
            for kk in range(SUB):
                jj = s * SUB + kk
                i = b * start_stride + jj * item_stride
                ii = wp.min(i, n_pts - 1)
                p = _xform(T, src[ii])
                t = int(-1)
                if i < n_pts and jj < count:
                    if wp.static(projective):
                        t = _project_assoc(src[ii], p, sn[ii], T, tp, tn, th, tw, fx, fy, cx, cy, max_d, cos_min)
                    else:
                        t = idx[ii]
                # Skip unmatched points with `continue` (no locals assigned under a branch, which Warp would copy;
                # measured a few % faster than accumulating zeros for them).
                if t < 0:
                    continue
                m = 1.0
                nq = tn[t]
                d = p - tp[t]
                r = wp.dot(nq, d)
                c = wp.cross(p, nq)
                w = _robust_w(r, kind, k)
                J = wp.spatial_vectorf(c[0], c[1], c[2], nq[0], nq[1], nq[2])
                part += _contrib(J, w, r, w * r * r, wp.length_sq(d), m, wp.abs(r), 0.0, 0.0)
                if wp.static(photo):
                    ri = float(0.0)
                    gu = float(0.0)
                    gv = float(0.0)
                    mi = float(0.0)
                    z = wp.where(p[2] > 0.0, p[2], 1.0)
                    u = fx * p[0] / z + cx
                    v = fy * p[1] / z + cy
                    fu = wp.floor(u)
                    fv = wp.floor(v)
                    if t >= 0 and fu >= 0.0 and fv >= 0.0 and fu + 1.0 <= float(t_int.shape[1] - 1):
                        if fv + 1.0 <= float(t_int.shape[0] - 1):
                            mi = 1.0
                            ri = lam * (_bilinear1(t_int, u, v) - s_int[ii])
                            gu = _bilinear1(t_gu, u, v)
                            gv = _bilinear1(t_gv, u, v)
                    dp = wp.vec3(gu * fx / z, gv * fy / z, -(gu * fx * p[0] + gv * fy * p[1]) / (z * z))
                    cp = wp.cross(p, dp)
                    JI = wp.spatial_vectorf(cp[0], cp[1], cp[2], dp[0], dp[1], dp[2]) * lam
                    part += _contrib(JI, 1.0, ri, 0.0, 0.0, 0.0, 0.0, ri * ri, mi)
            for q in range(33):
                acc[q] += wp.float64(part[q])
        # Unpack: symmetric 6x6 from the upper triangle, then Jtr and the extras (layout in kernels.icp).
        n = int(0)
        for r0 in range(6):
            for c0 in range(r0, 6):
                out[b, r0 * 6 + c0] = acc[n]
                out[b, c0 * 6 + r0] = acc[n]
                n += 1
        for q in range(6):
            out[b, 36 + q] = acc[21 + q]
        out[b, 42] = acc[27]
        out[b, 43] = acc[28]
        out[b, 44] = acc[29]
        out[b, 47] = acc[30]
        out[b, 45] = acc[31]
        out[b, 46] = acc[32]

    return _reduce


_REDUCE: dict = {}
# CUDA threads per block of the reduction: its 146-160 registers per thread (sm_86 / sm_87 cubins, docs/gpu.md)
# leave room for 12 resident warps per multiprocessor, which 256-thread blocks (8 warps) cannot fill; 128-thread
# blocks can (25 % instead of 17 % occupancy).
REDUCE_GPU_BLOCK = 128
GPU_BLOCKS = {"_reduce": REDUCE_GPU_BLOCK}  # CUDA threads per block where not Warp's 256 (perf/gpu_codegen.py)


def _reduce_kernel(projective: bool, photo: bool):
    key = (projective, photo)
    if key not in _REDUCE:
        _REDUCE[key] = _make_reduce(projective, photo)
    return _REDUCE[key]


def aot_kernels() -> dict:
    """label -> kernel for the factory-made kernels (each its own Warp module), for ahead-of-time builds
    (perf/gpu_codegen.py)."""
    return {f"_reduce[{'projective' if p else 'idx'}{'+photo' if ph else ''}]": _reduce_kernel(p, ph)
            for p in (False, True) for ph in (False, True)}


def reduce_point_to_plane(src, T, tp, tn, idx, kind: int, k: float, photo, device: str, proj=None):
    """proj = (source_normals, camera, H, W, max_d, cos_min) fuses projective association into the pass (idx unused)."""
    n = src.shape[0]
    blocks, start_stride, item_stride, count = n_blocks(n, device)
    # every block writes its whole row, so no zero fill (a [16384, 48] float64 memset per call on CUDA)
    out = (torch.empty if n else torch.zeros)(blocks, N_SLOTS, dtype=torch.float64, device=src.device)
    r = reduce_terms(src, photo, proj)
    if n:
        _launch(_reduce_kernel(bool(r.projective), bool(r.has_photo)), blocks,
                [_arr(src, dtype=wp.vec3), _mat(T), _arr(tp, dtype=wp.vec3),
                 _arr(tn, dtype=wp.vec3), _arr(idx), kind, k, _arr(r.s_int),
                 _arr(r.t_int), _arr(r.gu), _arr(r.gv), r.fx, r.fy, r.cx, r.cy, r.lam,
                 _arr(r.sn, dtype=wp.vec3), r.th, r.tw, r.max_d, r.cos_min, 0,
                 start_stride, item_stride, count, _arr(out)], 21, device, work=n, gpu_block=REDUCE_GPU_BLOCK)
        _sync(device)
    return out.sum(0)
