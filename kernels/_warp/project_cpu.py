"""CPU projection kernels of the Warp rasteriser, written for the CPU's vector units.

kernels/_warp/project.py projects one Gaussian at a time with branches (culling, early returns) and strided array
indexing, which Warp's CPU code generator emits as scalar code: ~50 ns per Gaussian forward and ~130 ns backward
at 320x240 / 60k Gaussians, a sixth of a mapping iteration. These kernels do the same per block of BLOCK Gaussians
(one kernel thread, as there) in three passes over sub-blocks of SUB: gather the inputs (and, backward, sum the
Gaussian's tile-entry gradients) into local arrays, one branch-free pass of the math (culling as masks) that the
CPU compiler vectorises (8 float lanes with AVX2 / AVX-512, 4 with SSE / NEON), and a pass that writes the rows.
Same rules and outputs as kernels/_warp/project.py up to float32 rounding (multiply-adds fuse here, and the
viewmat parts of a block are summed in 8 lanes before they are added): tests/test_raster.py compares the two.
The block's viewmat part goes to g_view[b] as there, so kernels/_warp/project.py's _view_grad sums them unchanged.
It is a CPU kernel only: on CUDA one thread per Gaussian (kernels/_warp/project.py) is the right shape.
"""

from __future__ import annotations

import warp as wp

CPU_ONLY = True  # perf/gpu_codegen.py does not build this module for CUDA

wp.set_module_options({"enable_backward": False, "max_unroll": 0, "cpu_compiler_flags": (
    "-march=native -ffp-contract=fast -mllvm=-inline-threshold=9000 -mllvm=-inline-cold-callsite-threshold=3000")})

_COMMON = r"""
    const int SUB = 64;
    const int i_end = (i0 + count < n ? i0 + count : n);
    auto F2 = [](const wp::array_t<float>& a, int i, int j) -> float {
        return *(const float*)((const char*)a.data + (size_t)i * a.strides[0] + (size_t)j * a.strides[1]);
    };
    auto F1 = [](const wp::array_t<float>& a, int i) -> float {
        return *(const float*)((const char*)a.data + (size_t)i * a.strides[0]);
    };
    auto I1 = [](const wp::array_t<int>& a, int i) -> int {
        return *(const int*)((const char*)a.data + (size_t)i * a.strides[0]);
    };
    float Rv[9];  // the viewmat's rotation, row-major
    for (int k = 0; k < 9; ++k) Rv[k] = F2(view, k / 3, k % 3);
    const float R00 = Rv[0], R01 = Rv[1], R02 = Rv[2], R10 = Rv[3], R11 = Rv[4], R12 = Rv[5];
    const float R20 = Rv[6], R21 = Rv[7], R22 = Rv[8];
    // 3x3 row-major helpers (inlined into the vector loops, their arrays become registers)
    auto rotmat = [](float w, float x, float y, float z, float* Q) {  // unit quaternion wxyz -> rotation
        Q[0] = 1.0f - 2.0f * (y * y + z * z); Q[1] = 2.0f * (x * y - w * z); Q[2] = 2.0f * (x * z + w * y);
        Q[3] = 2.0f * (x * y + w * z); Q[4] = 1.0f - 2.0f * (x * x + z * z); Q[5] = 2.0f * (y * z - w * x);
        Q[6] = 2.0f * (x * z - w * y); Q[7] = 2.0f * (y * z + w * x); Q[8] = 1.0f - 2.0f * (x * x + y * y);
    };
    auto mul33 = [](const float* A, const float* B, bool ta, float* C) {  // C = A B, or A^T B with ta
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) {
                float s = 0.0f;
                for (int k = 0; k < 3; ++k) s += (ta ? A[3 * k + r] : A[3 * r + k]) * B[3 * k + c];
                C[3 * r + c] = s;
            }
    };
    const float t0 = F2(view, 0, 3), t1 = F2(view, 1, 3), t2 = F2(view, 2, 3);
    const float lim_x = 0.15f * (float)width / fx;
    const float lim_y = 0.15f * (float)height / fy;
    const float u_lo = -(cx / fx + lim_x), u_hi = ((float)width - cx) / fx + lim_x;
    const float v_lo = -(cy / fy + lim_y), v_hi = ((float)height - cy) / fy + lim_y;
    auto clampf = [](float x, float a, float b) -> float { x = x > a ? x : a; return x < b ? x : b; };
"""

_FORWARD = _COMMON + r"""
    const float ntx = (float)((width + 15) / 16), nty = (float)((height + 15) / 16);
    alignas(64) float IN[14][SUB];  // mean xyz, quat wxyz, scale xyz, opacity, colour rgb
    alignas(64) float OUT[10][SUB];  // the projected row (kernels.raster.PACKED)
    alignas(64) int RI[6][SUB];  // radius, rect x0 y0 x1 y1, ntiles
    alignas(64) float LO[SUB];
    for (int b0 = i0; b0 < i_end; b0 += SUB) {
        const int m = (b0 + SUB < i_end ? b0 + SUB : i_end) - b0;
        for (int t = 0; t < m; ++t) {
            const int i = b0 + t;
            for (int k = 0; k < 3; ++k) IN[k][t] = F2(means, i, k);
            for (int k = 0; k < 4; ++k) IN[3 + k][t] = F2(quats, i, k);
            for (int k = 0; k < 3; ++k) IN[7 + k][t] = F2(scales, i, k);
            IN[10][t] = F1(opac, i);
            for (int k = 0; k < 3; ++k) IN[11 + k][t] = F2(colors, i, k);
            LO[t] = -wp::log(255.0f * IN[10][t]) - 1e-5f;  // the exp() skip threshold pthr
        }
        for (int t = 0; t < m; ++t) {
            const float FMAX = 3.4028234663852886e38f;
            bool valid = IN[10][t] >= 0.0f && IN[10][t] <= 1.0f;
            for (int k = 0; k < 14; ++k) valid = valid && fabsf(IN[k][t]) <= FMAX;
            const float mx3 = IN[0][t], my3 = IN[1][t], mz3 = IN[2][t];
            const float qw = IN[3][t], qx = IN[4][t], qy = IN[5][t], qz = IN[6][t];
            const float sx = IN[7][t], sy = IN[8][t], sz = IN[9][t];
            const float qlen2 = qw * qw + qx * qx + qy * qy + qz * qz;
            valid = valid && qlen2 >= 1e-20f;
            const float px = R00 * mx3 + R01 * my3 + R02 * mz3 + t0;
            const float py = R10 * mx3 + R11 * my3 + R12 * mz3 + t1;
            const float z = R20 * mx3 + R21 * my3 + R22 * mz3 + t2;
            bool vis = valid && z >= near && z <= far;
            const float inv_z = 1.0f / z;
            const float u = clampf(px * inv_z, u_lo, u_hi), v = clampf(py * inv_z, v_lo, v_hi);
            const float qn = 1.0f / sqrtf(qlen2);
            const float w = qw * qn, x = qx * qn, y = qy * qn, zq = qz * qn;
            float Q[9], Nm[9];
            rotmat(w, x, y, zq, Q);
            mul33(Rv, Q, false, Nm);
            // Mc = Rv Rq diag(s)
            const float M00 = Nm[0] * sx, M01 = Nm[1] * sy, M02 = Nm[2] * sz;
            const float M10 = Nm[3] * sx, M11 = Nm[4] * sy, M12 = Nm[5] * sz;
            const float M20 = Nm[6] * sx, M21 = Nm[7] * sy, M22 = Nm[8] * sz;
            const float f0 = fx * inv_z, f1 = fy * inv_z;
            const float A0 = f0 * (M00 - u * M20), A1 = f0 * (M01 - u * M21), A2 = f0 * (M02 - u * M22);
            const float B0 = f1 * (M10 - v * M20), B1 = f1 * (M11 - v * M21), B2 = f1 * (M12 - v * M22);
            const float a = A0 * A0 + A1 * A1 + A2 * A2 + 0.3f;
            const float b = A0 * B0 + A1 * B1 + A2 * B2;
            const float c = B0 * B0 + B1 * B1 + B2 * B2 + 0.3f;
            const float det = a * c - b * b;
            vis = vis && det > 0.0f;
            const float mx = fx * px * inv_z + cx, my = fy * py * inv_z + cy;
            const float mid = 0.5f * (a + c);
            const float dd = mid * mid - det;
            const float r = ceilf(3.0f * sqrtf(mid + sqrtf(dd > 0.1f ? dd : 0.1f)));
            const float x0 = clampf(floorf((mx - r) / 16.0f), 0.0f, ntx);
            const float x1 = clampf(floorf((mx + r) / 16.0f) + 1.0f, 0.0f, ntx);
            const float y0 = clampf(floorf((my - r) / 16.0f), 0.0f, nty);
            const float y1 = clampf(floorf((my + r) / 16.0f) + 1.0f, 0.0f, nty);
            vis = vis && x1 > x0 && y1 > y0;  // false for NaN as well
            // the tiles listed: the radius' rectangle cut to the box of the alpha >= 1/255 ellipse (widened as the
            // compositing widens it; pixel centres at integers), which no composited pixel leaves
            const float lo = LO[t];
            const bool lists = lo < 0.0f;
            const float lgm = -1.01f * lo + 0.01f;
            const float ex = sqrtf(2.0f * lgm * a), ey = sqrtf(2.0f * lgm * c);
            float tx0 = floorf(ceilf(mx - ex) / 16.0f), tx1 = floorf(floorf(mx + ex) / 16.0f) + 1.0f;
            float ty0 = floorf(ceilf(my - ey) / 16.0f), ty1 = floorf(floorf(my + ey) / 16.0f) + 1.0f;
            tx0 = x0 > tx0 ? x0 : tx0; tx1 = x1 < tx1 ? x1 : tx1;
            ty0 = y0 > ty0 ? y0 : ty0; ty1 = y1 < ty1 ? y1 : ty1;
            const bool tiles = vis && lists && tx1 > tx0 && ty1 > ty0;
            const float inv_det = 1.0f / det;
            OUT[0][t] = vis ? mx : 0.0f;
            OUT[1][t] = vis ? my : 0.0f;
            OUT[2][t] = vis ? c * inv_det : 0.0f;
            OUT[3][t] = vis ? -b * inv_det : 0.0f;
            OUT[4][t] = vis ? a * inv_det : 0.0f;
            OUT[5][t] = vis ? IN[10][t] : 0.0f;
            OUT[6][t] = vis ? IN[11][t] : 0.0f;
            OUT[7][t] = vis ? IN[12][t] : 0.0f;
            OUT[8][t] = vis ? IN[13][t] : 0.0f;
            OUT[9][t] = vis ? z : 0.0f;
            const int ix0 = tiles ? (int)tx0 : 0, ix1 = tiles ? (int)tx1 : 0;
            const int iy0 = tiles ? (int)ty0 : 0, iy1 = tiles ? (int)ty1 : 0;
            RI[0][t] = vis ? (int)(r < 1073741824.0f ? r : 1073741824.0f) : 0;
            RI[1][t] = ix0; RI[2][t] = iy0; RI[3][t] = ix1; RI[4][t] = iy1;
            RI[5][t] = valid ? (ix1 - ix0) * (iy1 - iy0) : -1;
        }
        for (int t = 0; t < m; ++t) {
            const int i = b0 + t;
            float* row = (float*)((char*)proj.data + (size_t)i * proj.strides[0]);
            const size_t pj = proj.strides[1] / sizeof(float);
            for (int k = 0; k < 10; ++k) row[k * pj] = OUT[k][t];
            *(int*)((char*)radius.data + (size_t)i * radius.strides[0]) = RI[0][t];
            int* rr = (int*)((char*)rect.data + (size_t)i * rect.strides[0]);
            const size_t rj = rect.strides[1] / sizeof(int);
            for (int k = 0; k < 4; ++k) rr[k * rj] = RI[1 + k][t];
            *(int*)((char*)ntiles.data + (size_t)i * ntiles.strides[0]) = RI[5][t];
            *(float*)((char*)pthr.data + (size_t)i * pthr.strides[0]) = RI[0][t] > 0 ? LO[t] : 0.0f;
        }
    }
"""

_BACKWARD = _COMMON + r"""
    const int PREFETCH = 6;  // Gaussians ahead whose tile-entry gradient rows are fetched into cache
    alignas(64) float IN[13][SUB];  // mean xyz, quat wxyz, scale xyz, conic a b c
    alignas(64) float GE[10][SUB];  // the row gradient: sum of the Gaussian's tile entries' gradients
    alignas(64) float OUT[10][SUB];  // g_means xyz, g_quats wxyz, g_scales xyz
    alignas(64) float VP[12][SUB];  // viewmat part: rotation row-major, then translation
    alignas(64) int NT[SUB];
    alignas(32) float acc[12][8];
    for (int k = 0; k < 12; ++k)
        for (int l = 0; l < 8; ++l) acc[k][l] = 0.0f;
    const char* gbase = (const char*)g_entry.data;
    const size_t gs0 = g_entry.strides[0], gs1 = g_entry.strides[1];
    auto prefetch = [&](int j) {
        const int nt = I1(ntiles, j);
        const int k0 = I1(emit_start, j);
        for (int k = k0; k < k0 + (nt < 8 ? nt : 8); ++k) {
            const char* row = gbase + (size_t)I1(emit_pos, k) * gs0;
            __builtin_prefetch(row);
            __builtin_prefetch(row + 9 * gs1);
        }
    };
    for (int j = i0; j < i0 + PREFETCH && j < i_end; ++j) prefetch(j);
    for (int b0 = i0; b0 < i_end; b0 += SUB) {
        const int m = (b0 + SUB < i_end ? b0 + SUB : i_end) - b0;
        for (int t = 0; t < m; ++t) {
            const int i = b0 + t;
            if (i + PREFETCH < i_end) prefetch(i + PREFETCH);
            const int nt = I1(ntiles, i);
            NT[t] = nt;
            float s[10] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
            if (nt > 0) {
                const int k0 = I1(emit_start, i);
                for (int k = k0; k < k0 + nt; ++k) {
                    const char* row = gbase + (size_t)I1(emit_pos, k) * gs0;
                    for (int j = 0; j < 10; ++j) s[j] += *(const float*)(row + (size_t)j * gs1);
                }
            }
            for (int j = 0; j < 10; ++j) GE[j][t] = s[j];
            for (int k = 0; k < 3; ++k) IN[k][t] = F2(means, i, k);
            for (int k = 0; k < 4; ++k) IN[3 + k][t] = F2(quats, i, k);
            for (int k = 0; k < 3; ++k) IN[7 + k][t] = F2(scales, i, k);
            for (int k = 0; k < 3; ++k) IN[10 + k][t] = F2(proj, i, 2 + k);
        }
        for (int t = 0; t < m; ++t) {
            const bool live = NT[t] > 0;
            const float mx3 = IN[0][t], my3 = IN[1][t], mz3 = IN[2][t];
            const float px = R00 * mx3 + R01 * my3 + R02 * mz3 + t0;
            const float py = R10 * mx3 + R11 * my3 + R12 * mz3 + t1;
            const float pz = R20 * mx3 + R21 * my3 + R22 * mz3 + t2;
            const float inv_z = 1.0f / (live ? pz : 1.0f);
            const float ru = px * inv_z, rv = py * inv_z;
            const float u = clampf(ru, u_lo, u_hi), v = clampf(rv, v_lo, v_hi);
            const float qw = IN[3][t], qx = IN[4][t], qy = IN[5][t], qz = IN[6][t];
            const float ql2 = qw * qw + qx * qx + qy * qy + qz * qz;
            const float qlen = sqrtf(live ? ql2 : 1.0f);
            const float w = qw / qlen, x = qx / qlen, y = qy / qlen, z = qz / qlen;
            float Q[9], Nm[9];
            rotmat(w, x, y, z, Q);
            mul33(Rv, Q, false, Nm);  // N = Rv Rq; Mc = N diag(s)
            const float Q00 = Q[0], Q01 = Q[1], Q02 = Q[2], Q10 = Q[3], Q11 = Q[4], Q12 = Q[5];
            const float Q20 = Q[6], Q21 = Q[7], Q22 = Q[8];
            const float N00 = Nm[0], N01 = Nm[1], N02 = Nm[2], N10 = Nm[3], N11 = Nm[4], N12 = Nm[5];
            const float N20 = Nm[6], N21 = Nm[7], N22 = Nm[8];
            const float sx = IN[7][t], sy = IN[8][t], sz = IN[9][t];
            const float M00 = N00 * sx, M01 = N01 * sy, M02 = N02 * sz;
            const float M10 = N10 * sx, M11 = N11 * sy, M12 = N12 * sz;
            const float M20 = N20 * sx, M21 = N21 * sy, M22 = N22 * sz;
            const float f0 = fx * inv_z, f1 = fy * inv_z;
            const float A0 = f0 * (M00 - u * M20), A1 = f0 * (M01 - u * M21), A2 = f0 * (M02 - u * M22);
            const float B0 = f1 * (M10 - v * M20), B1 = f1 * (M11 - v * M21), B2 = f1 * (M12 - v * M22);
            // conic = inverse(cov2d): dL/dcov2d = -Q G Q (b counted on both off-diagonals)
            const float A = IN[10][t], B = IN[11][t], C = IN[12][t];
            const float gA = GE[2][t], gB = GE[3][t], gC = GE[4][t];
            const float ga = -(A * A * gA + A * B * gB + B * B * gC);
            const float gb = -(2.0f * A * B * gA + (A * C + B * B) * gB + 2.0f * B * C * gC);
            const float gc = -(B * B * gA + B * C * gB + C * C * gC);
            const float gT00 = 2.0f * ga * A0 + gb * B0, gT01 = 2.0f * ga * A1 + gb * B1, gT02 = 2.0f * ga * A2 + gb * B2;
            const float gT10 = gb * A0 + 2.0f * gc * B0, gT11 = gb * A1 + 2.0f * gc * B1, gT12 = gb * A2 + 2.0f * gc * B2;
            const float gM00 = f0 * gT00, gM01 = f0 * gT01, gM02 = f0 * gT02;
            const float gM10 = f1 * gT10, gM11 = f1 * gT11, gM12 = f1 * gT12;
            const float uf0 = u * f0, vf1 = v * f1;
            const float gM20 = -uf0 * gT00 - vf1 * gT10, gM21 = -uf0 * gT01 - vf1 * gT11;
            const float gM22 = -uf0 * gT02 - vf1 * gT12;
            const float g_mx = GE[0][t], g_my = GE[1][t];
            float g_inv_z = (gT00 * A0 + gT01 * A1 + gT02 * A2 + gT10 * B0 + gT11 * B1 + gT12 * B2) * pz;
            float gx = g_mx * f0, gy = g_my * f1;
            g_inv_z += g_mx * fx * px + g_my * fy * py;
            // the 1.3 x field-of-view clamp passes gradients only where it is not active
            const float gu = -f0 * (gT00 * M20 + gT01 * M21 + gT02 * M22);
            const float gv = -f1 * (gT10 * M20 + gT11 * M21 + gT12 * M22);
            const bool fu = ru == u, fv = rv == v;
            gx += fu ? gu * inv_z : 0.0f;
            g_inv_z += fu ? gu * px : 0.0f;
            gy += fv ? gv * inv_z : 0.0f;
            g_inv_z += fv ? gv * py : 0.0f;
            const float gz = GE[9][t] - g_inv_z * inv_z * inv_z;
            // gN = gMc diag(s); dL/ds_j = sum_r gMc[r, j] N[r, j]
            const float gN00 = gM00 * sx, gN01 = gM01 * sy, gN02 = gM02 * sz;
            const float gN10 = gM10 * sx, gN11 = gM11 * sy, gN12 = gM12 * sz;
            const float gN20 = gM20 * sx, gN21 = gM21 * sy, gN22 = gM22 * sz;
            OUT[7][t] = gM00 * N00 + gM10 * N10 + gM20 * N20;
            OUT[8][t] = gM01 * N01 + gM11 * N11 + gM21 * N21;
            OUT[9][t] = gM02 * N02 + gM12 * N12 + gM22 * N22;
            const float gN[9] = {gN00, gN01, gN02, gN10, gN11, gN12, gN20, gN21, gN22};
            float Gm[9];
            mul33(Rv, gN, true, Gm);  // G = Rv^T gN = dL/dRq
            const float G00 = Gm[0], G01 = Gm[1], G02 = Gm[2], G10 = Gm[3], G11 = Gm[4], G12 = Gm[5];
            const float G20 = Gm[6], G21 = Gm[7], G22 = Gm[8];
            const float gw = 2.0f * (-z * G01 + y * G02 + z * G10 - x * G12 - y * G20 + x * G21);
            const float gxq = 2.0f * (y * G01 + z * G02 + y * G10 - 2.0f * x * G11 - w * G12 + z * G20 + w * G21
                                      - 2.0f * x * G22);
            const float gyq = 2.0f * (-2.0f * y * G00 + x * G01 + w * G02 + x * G10 + z * G12 - w * G20 + z * G21
                                      - 2.0f * y * G22);
            const float gzq = 2.0f * (-2.0f * z * G00 - w * G01 + x * G02 + w * G10 - 2.0f * z * G11 + y * G12
                                      + x * G20 + y * G21);
            const float dot = w * gw + x * gxq + y * gyq + z * gzq;
            OUT[3][t] = (gw - w * dot) / qlen;
            OUT[4][t] = (gxq - x * dot) / qlen;
            OUT[5][t] = (gyq - y * dot) / qlen;
            OUT[6][t] = (gzq - z * dot) / qlen;
            // dL/dmeans = Rv^T gp
            OUT[0][t] = R00 * gx + R10 * gy + R20 * gz;
            OUT[1][t] = R01 * gx + R11 * gy + R21 * gz;
            OUT[2][t] = R02 * gx + R12 * gy + R22 * gz;
            // viewmat part: gN Rq^T + gp m^T, then gp
            VP[0][t] = gN00 * Q00 + gN01 * Q01 + gN02 * Q02 + gx * mx3;
            VP[1][t] = gN00 * Q10 + gN01 * Q11 + gN02 * Q12 + gx * my3;
            VP[2][t] = gN00 * Q20 + gN01 * Q21 + gN02 * Q22 + gx * mz3;
            VP[3][t] = gN10 * Q00 + gN11 * Q01 + gN12 * Q02 + gy * mx3;
            VP[4][t] = gN10 * Q10 + gN11 * Q11 + gN12 * Q12 + gy * my3;
            VP[5][t] = gN10 * Q20 + gN11 * Q21 + gN12 * Q22 + gy * mz3;
            VP[6][t] = gN20 * Q00 + gN21 * Q01 + gN22 * Q02 + gz * mx3;
            VP[7][t] = gN20 * Q10 + gN21 * Q11 + gN22 * Q12 + gz * my3;
            VP[8][t] = gN20 * Q20 + gN21 * Q21 + gN22 * Q22 + gz * mz3;
            VP[9][t] = gx;
            VP[10][t] = gy;
            VP[11][t] = gz;
            for (int k = 0; k < 10; ++k) OUT[k][t] = live ? OUT[k][t] : 0.0f;
            for (int k = 0; k < 12; ++k) VP[k][t] = live ? VP[k][t] : 0.0f;
        }
        // the block's viewmat part, in 8 lanes (lanes past m hold zeros)
        for (int t = m; t < ((m + 7) & ~7); ++t)
            for (int k = 0; k < 12; ++k) VP[k][t] = 0.0f;
        for (int k = 0; k < 12; ++k)
            for (int t = 0; t < m; t += 8)
                for (int l = 0; l < 8; ++l) acc[k][l] += VP[k][t + l];
        for (int t = 0; t < m; ++t) {
            const int i = b0 + t;
            auto put = [&](const wp::array_t<float>& a, int j, float val) {
                *(float*)((char*)a.data + (size_t)i * a.strides[0] + (size_t)j * a.strides[1]) = val;
            };
            for (int k = 0; k < 3; ++k) put(g_means, k, OUT[k][t]);
            for (int k = 0; k < 4; ++k) put(g_quats, k, OUT[3 + k][t]);
            for (int k = 0; k < 3; ++k) put(g_scales, k, OUT[7 + k][t]);
            for (int k = 0; k < 3; ++k) put(g_colors, k, GE[6 + k][t]);
            *(float*)((char*)g_opac.data + (size_t)i * g_opac.strides[0]) = GE[5][t];
        }
    }
    for (int k = 0; k < 12; ++k) {
        float s = 0.0f;
        for (int l = 0; l < 8; ++l) s += acc[k][l];
        *(float*)((char*)g_view.data + (size_t)blk * g_view.strides[0] + (size_t)k * g_view.strides[1]) = s;
    }
"""


@wp.func_native(_FORWARD)
def _fwd_block(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
               opac: wp.array(dtype=float), colors: wp.array2d(dtype=float), view: wp.array2d(dtype=float),
               fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
               i0: int, count: int, n: int, proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
               rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), pthr: wp.array(dtype=float)):
    ...


@wp.func_native(_BACKWARD)
def _bwd_block(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
               view: wp.array2d(dtype=float), fx: float, fy: float, cx: float, cy: float, width: int, height: int,
               i0: int, count: int, n: int, blk: int, proj: wp.array2d(dtype=float), ntiles: wp.array(dtype=wp.int32),
               emit_start: wp.array(dtype=wp.int32), emit_pos: wp.array(dtype=wp.int32),
               g_entry: wp.array2d(dtype=float), g_means: wp.array2d(dtype=float), g_quats: wp.array2d(dtype=float),
               g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float), g_colors: wp.array2d(dtype=float),
               g_view: wp.array2d(dtype=float)):
    ...


# The same argument lists as kernels/_warp/project.py's _project_fwd_blocks and _project_bwd (its launches take
# either): thread = Gaussians [count (tid + offset), + count).
@wp.kernel
def forward_blocks(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                   opac: wp.array(dtype=float), colors: wp.array2d(dtype=float), view: wp.array2d(dtype=float),
                   fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                   offset: int, count: int, n: int, proj: wp.array2d(dtype=float), radius: wp.array(dtype=wp.int32),
                   rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), pthr: wp.array(dtype=float)):
    _fwd_block(means, quats, scales, opac, colors, view, fx, fy, cx, cy, width, height, near, far,
               (wp.tid() + offset) * count, count, n, proj, radius, rect, ntiles, pthr)


@wp.kernel
def backward_blocks(means: wp.array2d(dtype=float), quats: wp.array2d(dtype=float), scales: wp.array2d(dtype=float),
                    view: wp.array2d(dtype=float), fx: float, fy: float, cx: float, cy: float, width: int,
                    height: int, offset: int, count: int, n: int, proj: wp.array2d(dtype=float),
                    ntiles: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32),
                    emit_pos: wp.array(dtype=wp.int32), g_entry: wp.array2d(dtype=float),
                    g_means: wp.array2d(dtype=float), g_quats: wp.array2d(dtype=float),
                    g_scales: wp.array2d(dtype=float), g_opac: wp.array(dtype=float),
                    g_colors: wp.array2d(dtype=float), g_view: wp.array2d(dtype=float)):
    b = wp.tid() + offset
    _bwd_block(means, quats, scales, view, fx, fy, cx, cy, width, height, b * count, count, n, b, proj, ntiles,
               emit_start, emit_pos, g_entry, g_means, g_quats, g_scales, g_opac, g_colors, g_view)
