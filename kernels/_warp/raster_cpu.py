"""CPU compositing kernels of the Warp rasteriser, written for the CPU's vector units.

kernels/_warp/raster.py composites one pixel at a time: a Gaussian-pixel pair costs ~26 ns forward and ~36 ns
backward there, because Warp's CPU code generator emits scalar code with strided array indexing that LLVM cannot
vectorise. These kernels do the same work per 16x16 tile, with the same rules and the same outputs, but keep the
tile's per-pixel state in local arrays laid out in 4x4-pixel blocks of 16 lanes and composite a Gaussian over the
blocks its ellipse's bounding box reaches, with branch-free code (masks instead of branches, a polynomial exp),
which the CPU compiler (Warp builds CPU modules with -O3 -march=native; here with FMA contraction and a preference
for 512-bit vectors) turns into one 16-lane AVX-512 instruction per step (two 8-lane AVX2, four SSE / NEON ones
elsewhere). Lanes outside the ellipse fail the per-pixel test like any other pixel.
Why 4x4 blocks: the mapping scenes' Gaussians are a few pixels across; at 320x240 with 60k of them an entry's
ellipse reaches 3.95 blocks of 4x4 on average against 7.83 groups of 8 pixels of one row (the layout before) and
5.85 rows of 16, so a 16-lane step wastes the fewest lanes in this shape. On one mapping step's inputs at
320x240 / 60k, one thread, thread CPU time, both layouts interleaved in one process (Intel Xeon, AVX-512):
forward 15.6 -> 11.7 ms with the same outputs bit for bit (every pixel sees the same arithmetic), backward
22.2 -> 18.0 ms (the per-entry sums are a tree over 16 lanes now, so the gradients' rounding differs, ~1e-7
relative).
The backward's per-entry lane sums run as whole-vector adds in registers (16 -> 8 -> 4 lanes, then 2 + 2): a
loop over the halves compiled to masked loads of just-stored data, which the store buffer cannot forward (3.5 ms
of a 22 ms backward went there).
The per-tile set-up and write-out loops read and write the images row by row through plain pointers (an image
gradient is contiguous or a broadcast scalar, which reads from a row of its value), so they vectorise too (at
160x120 with 1k Gaussians, scalar, they cost ~0.1 of the compositing's ~0.48 ms).

The tile body is a native C++ snippet (`wp.func_native`) inside an ordinary Warp kernel: Warp still compiles,
caches and launches it, and kernels/_warp/raster.py cuts the tiles into chunks over the cores as before. It is a
CPU kernel only: on CUDA one thread per pixel (kernels/_warp/raster.py) is the right shape and stays in use.

Per-pixel rules (identical to kernels/_warp/raster.py and to the twin kernels.reference.rasterize_reference):
power = -0.5 (a dx^2 + c dy^2) - b dx dy must lie in [lo, 0] (lo = log(1/255 / opacity), pthr), alpha =
min(0.99, opacity exp(power)) >= 1/255, and a pixel stops before the Gaussian that would take its transmittance
below 1e-4. exp is a degree-7 polynomial after Cody-Waite range reduction, relative error 1.2e-7 on [-20, 0] (expf's
float32 result: 2e-7), clamped to exp(-20) below: a pixel is only composited for power >= lo >= log(1/255) = -5.5
(opacity <= 1), and the clamp keeps the far lanes of a group off denormal numbers, which cost ~100 cycles on x86.
"""

from __future__ import annotations

import warp as wp

CPU_ONLY = True  # perf/gpu_codegen.py does not build this module for CUDA

# Warp's default CPU flags plus -ffp-contract=fast (multiply-adds fuse to FMA: the polynomial and the accumulators)
# and 512-bit vectors where the CPU has them (LLVM prefers 256 bits on AVX-512 CPUs; the 16-lane loops want 512)
wp.set_module_options({"enable_backward": False, "max_unroll": 0, "cpu_compiler_flags": (
    "-march=native -mprefer-vector-width=512 -ffp-contract=fast -mllvm=-inline-threshold=9000"
    " -mllvm=-inline-cold-callsite-threshold=3000 -mllvm=-slp-recursion-max-depth=4")})

_COMMON = r"""
    typedef float f16v __attribute__((vector_size(64)));
    typedef float f8v __attribute__((vector_size(32)));
    typedef float f4v __attribute__((vector_size(16)));
    const int TS = 16;
    const int PREFETCH = 8;  // entries ahead whose projected row is fetched into cache (random-access misses)
    const float ALPHA_MIN = 1.0f / 255.0f;
    auto fexp = [](float x) -> float {
        // exp(x) for -20 <= x <= 0 (x is clamped to that range): x = n ln2 + r, |r| <= ln2 / 2
        x = x < 0.0f ? x : 0.0f;
        x = x > -20.0f ? x : -20.0f;
        float n = floorf(x * 1.44269504088896341f + 0.5f);
        float r = x - n * 0.693145751953125f;
        r = r - n * 1.42860682030941723e-06f;
        // exp(r) = 1 + r + r^2 P(r), P of degree 5 (Cephes' expf coefficients), in Estrin's form: a short
        // dependency chain (the loop is latency-bound)
        const float r2 = r * r;
        const float pa = 5.0000001201e-1f + 1.6666665459e-1f * r;
        const float pb = 4.1665795894e-2f + 8.3334519073e-3f * r;
        const float pc = 1.3981999507e-3f + 1.9875691500e-4f * r;
        const float p = (1.0f + r) + r2 * (pa + r2 * (pb + r2 * pc));
        int bits = ((int)n + 127) << 23;
        float scale;
        __builtin_memcpy(&scale, &bits, 4);
        return p * scale;
    };
    const int ty = t / tiles_x;
    const int tx = t - ty * tiles_x;
    const int x0 = tx * TS;
    const int y0 = ty * TS;
    const int nw = (x0 + TS < width ? x0 + TS : width) - x0;
    const int nh = (y0 + TS < height ? y0 + TS : height) - y0;
    const char* pbase = (const char*)proj.data;
    const size_t ps0 = proj.strides[0], ps1 = proj.strides[1];
    auto P = [&](int g, int j) -> float { return *(const float*)(pbase + (size_t)g * ps0 + (size_t)j * ps1); };
    auto F1 = [](const wp::array_t<float>& a, int i) -> float {
        return *(const float*)((const char*)a.data + (size_t)i * a.strides[0]);
    };
    auto I1 = [](const wp::array_t<int>& a, int i) -> int {
        return *(const int*)((const char*)a.data + (size_t)i * a.strides[0]);
    };
    const int s0 = I1(tile_start, t);
    const int s1 = I1(tile_start, t + 1);
    // rows [rlo, rhi] of the tile the ellipse d^T Q d <= 2 lgm reaches (lgm: the widened 1/255 threshold)
    auto rows_of = [&](float my, float ca, float det_q, float lgm, int& rlo, int& rhi) {
        float ey = sqrtf(2.0f * lgm * ca / det_q);
        float a = ceilf(my - ey), b = floorf(my + ey);
        a = a < (float)y0 ? (float)y0 : (a > (float)(y0 + nh) ? (float)(y0 + nh) : a);
        b = b < (float)(y0 - 1) ? (float)(y0 - 1) : (b > (float)(y0 + nh - 1) ? (float)(y0 + nh - 1) : b);
        rlo = (int)a;
        rhi = (int)b;
    };
    // columns [clo, chi] of the tile (clo > chi: none) that the ellipse's x extent can reach
    auto cols_of = [&](float mx, float cc, float det_q, float lgm, int& clo, int& chi) {
        float ex = sqrtf(2.0f * lgm * cc / det_q);
        float a = ceilf(mx - ex) - (float)x0, b = floorf(mx + ex) - (float)x0;
        a = a < 0.0f ? 0.0f : (a > (float)nw ? (float)nw : a);
        b = b < -1.0f ? -1.0f : (b > (float)(nw - 1) ? (float)(nw - 1) : b);
        clo = (int)a;
        chi = b < a ? clo - 1 : (int)b;
    };
    // the tile's per-pixel state is kept in 4x4-pixel blocks of 16 lanes (block row, block column, row, column)
    auto BI = [](int r, int c) -> int { return ((r >> 2) << 6) | ((c >> 2) << 4) | ((r & 3) << 2) | (c & 3); };
    // per lane of block row br: dy, and the terms -0.5 c dy^2 and b dy of the power
    auto block_row = [&](int br, float my, float cb, float cc, float* dyl, float* cdy, float* bdy) {
        for (int l = 0; l < 16; ++l) {
            const float dy = (float)(y0 + 4 * br + (l >> 2)) - my;
            dyl[l] = dy;
            cdy[l] = -0.5f * cc * dy * dy;
            bdy[l] = cb * dy;
        }
    };
    // body(base, fx0, bc, dyl, cdy, bdy) for every 4x4 block of the tile that the bounding box of an ellipse
    // (mean mx, my, conic a, b, c, det_q = a c - b^2, threshold lo) reaches: base = the block's first lane, bc its
    // column, fx0 = x0 - mx, and block_row's per-lane terms of its row
    auto for_blocks = [&](float mx, float my, float ca, float cb, float cc, float det_q, float lo, auto&& body) {
        const float lgm = -1.01f * lo + 0.01f;
        int rlo, rhi, clo, chi;
        rows_of(my, ca, det_q, lgm, rlo, rhi);
        cols_of(mx, cc, det_q, lgm, clo, chi);
        const float fx0 = (float)x0 - mx;
        for (int br = (rlo - y0) >> 2; rlo <= rhi && br <= (rhi - y0) >> 2; ++br) {
            alignas(64) float dyl[16], cdy[16], bdy[16];
            block_row(br, my, cb, cc, dyl, cdy, bdy);
            for (int bc = clo >> 2; bc <= chi >> 2; ++bc) body((br << 6) | (bc << 4), fx0, bc, dyl, cdy, bdy);
        }
    };
"""

_FORWARD = _COMMON + r"""
    alignas(64) float T[256];
    alignas(64) float CR[256];
    alignas(64) float CG[256];
    alignas(64) float CB[256];
    alignas(64) float DD[256];
    alignas(64) int LAST[256];
    for (int i = 0; i < 256; ++i) {
        // lanes outside the image start with T = 0: they never composite and are never written
        const int r = ((i >> 6) << 2) | ((i >> 2) & 3), c = (((i >> 4) & 3) << 2) | (i & 3);
        T[i] = (c < nw && r < nh) ? 1.0f : 0.0f;
        CR[i] = 0.0f; CG[i] = 0.0f; CB[i] = 0.0f; DD[i] = 0.0f; LAST[i] = 0;
    }
    const int npix = nw * nh;
    int done = 0;
    int* hits_p = (int*)hits.data;
    const size_t hs = hits.strides[0] / sizeof(int);
    for (int e = s0; e < s1; ++e) {
        alignas(64) int cntv[16] = {0};
        alignas(64) int finv[16] = {0};
        const int g = I1(entries, e);
        if (e + PREFETCH < s1) {  // entries are in depth order: their rows are scattered over the whole array
            const int gn = I1(entries, e + PREFETCH);
            __builtin_prefetch(pbase + (size_t)gn * ps0);
            __builtin_prefetch(pbase + (size_t)gn * ps0 + 9 * ps1);  // a 40-byte row can cross a cache line
            __builtin_prefetch((const char*)pthr.data + (size_t)gn * pthr.strides[0]);
        }
        const float lo = F1(pthr, g);
        const float ca = P(g, 2), cb = P(g, 3), cc = P(g, 4);
        const float det_q = ca * cc - cb * cb;
        if (done < npix && lo < 0.0f && det_q > 0.0f) {
            const float mx = P(g, 0), my = P(g, 1), op = P(g, 5);
            const float cr = P(g, 6), cg = P(g, 7), cbl = P(g, 8), z = P(g, 9);
            const int k1 = e - s0 + 1;
            for_blocks(mx, my, ca, cb, cc, det_q, lo, [&](int base, float fx0, int bc, const float* dyl,
                                                      const float* cdy, const float* bdy) {
                float* __restrict__ Tb = T + base;
                float* __restrict__ CRb = CR + base;
                float* __restrict__ CGb = CG + base;
                float* __restrict__ CBb = CB + base;
                float* __restrict__ DDb = DD + base;
                int* __restrict__ Lb = LAST + base;
                for (int l = 0; l < 16; ++l) {
                    const float Tj = Tb[l];
                    const float dx = fx0 + (float)(4 * bc + (l & 3));
                    const float power = -0.5f * ca * dx * dx + cdy[l] - bdy[l] * dx;
                    float a = op * fexp(power);
                    a = a < 0.99f ? a : 0.99f;
                    const bool valid = (Tj > 0.0f) & (power <= 0.0f) & (power >= lo) & (a >= ALPHA_MIN);
                    const float tT = Tj * (1.0f - a);
                    const bool stop = valid & (tT < 1e-4f);
                    const bool comp = valid & !stop;
                    const float w = comp ? a * Tj : 0.0f;
                    CRb[l] += w * cr;
                    CGb[l] += w * cg;
                    CBb[l] += w * cbl;
                    DDb[l] += w * z;
                    Tb[l] = stop ? -Tj : (comp ? tT : Tj);
                    Lb[l] = comp ? k1 : Lb[l];
                    cntv[l] += comp ? 1 : 0;
                    finv[l] += stop ? 1 : 0;
                }
            });
        }
        int count = 0, fin = 0;
        for (int l = 0; l < 16; ++l) { count += cntv[l]; fin += finv[l]; }
        done += fin;
        hits_p[(size_t)e * hs] = count;
    }
    const float bg0 = F1(bg, 0), bg1 = F1(bg, 1), bg2 = F1(bg, 2);
    for (int r = 0; r < nh; ++r) {
        const int q0 = (y0 + r) * width + x0;
        float* __restrict__ col = (float*)color.data + 3 * q0;
        float* __restrict__ dep = (float*)depth.data + q0;
        float* __restrict__ dno = (float*)dnorm.data + q0;
        float* __restrict__ alp = (float*)alpha.data + q0;
        float* __restrict__ tfi = (float*)t_final.data + q0;
        int* __restrict__ lst = (int*)last.data + q0;
        for (int j = 0; j < nw; ++j) {
            const int i = BI(r, j);
            const float Tv = fabsf(T[i]);
            const float a = 1.0f - Tv;
            tfi[j] = Tv;
            alp[j] = a;
            col[3 * j + 0] = CR[i] + Tv * bg0;
            col[3 * j + 1] = CG[i] + Tv * bg1;
            col[3 * j + 2] = CB[i] + Tv * bg2;
            dep[j] = DD[i];
            dno[j] = a > 1e-6f ? DD[i] / (a > 1e-6f ? a : 1.0f) : 0.0f;
            lst[j] = LAST[i];
        }
    }
"""

_BACKWARD = _COMMON + r"""
    alignas(64) float TR[256];
    alignas(64) float BH[256];
    alignas(64) float GR[256];
    alignas(64) float GG[256];
    alignas(64) float GB[256];
    alignas(64) float GD[256];
    alignas(64) int LAST[256];
    const float bg0 = F1(bg, 0), bg1 = F1(bg, 1), bg2 = F1(bg, 2);
    int n_live = 0;
    for (int i = 0; i < 256; ++i) {
        TR[i] = 1.0f; BH[i] = 0.0f; GR[i] = 0.0f; GG[i] = 0.0f; GB[i] = 0.0f; GD[i] = 0.0f; LAST[i] = 0;
    }
    // per-pixel inputs, row by row through plain pointers: an image gradient is either contiguous or a broadcast
    // scalar (stride 0, e.g. from a sum); a broadcast one reads from a row of its value
    alignas(64) float cst[4][48];
    auto rowp = [&](const wp::array_t<float>& a, int q0, int comp, int slot) -> const float* {
        if (a.strides[0] == 0) {
            const float v = *(const float*)a.data;
            for (int i = 0; i < 48; ++i) cst[slot][i] = v;
            return cst[slot];
        }
        return (const float*)a.data + (size_t)comp * q0;
    };
    for (int r = 0; r < nh; ++r) {
        const int q0 = (y0 + r) * width + x0;
        const float* __restrict__ tf = (const float*)t_final.data + q0;
        const float* __restrict__ dn = (const float*)dnorm.data + q0;
        const int* __restrict__ ls = (const int*)last.data + q0;
        const float* __restrict__ gdp = rowp(g_depth, q0, 1, 0);
        const float* __restrict__ gal = rowp(g_alpha, q0, 1, 1);
        const float* __restrict__ gdn = rowp(g_dnorm, q0, 1, 2);
        const float* __restrict__ gco = rowp(g_color, q0, 3, 3);
        int nl = 0;
        for (int j = 0; j < nw; ++j) {
            const int i = BI(r, j);
            const float TN = tf[j];
            const float a_px = 1.0f - TN;
            const bool ok = a_px > 1e-6f;
            const float gn = ok ? gdn[j] / (ok ? a_px : 1.0f) : 0.0f;
            const float gd = gdp[j] + gn;
            const float ga = gal[j] - gn * dn[j];
            const float gr = gco[3 * j + 0], gg = gco[3 * j + 1], gb = gco[3 * j + 2];
            GR[i] = gr; GG[i] = gg; GB[i] = gb; GD[i] = gd;
            TR[i] = TN;
            BH[i] = (gr * bg0 + gg * bg1 + gb * bg2 - ga) * TN;
            const int l = ls[j];
            LAST[i] = l;
            nl = l > nl ? l : nl;
        }
        n_live = nl > n_live ? nl : n_live;
    }
    char* gbase = (char*)g_entry.data;
    const size_t gs0 = g_entry.strides[0], gs1 = g_entry.strides[1];
    auto GE = [&](int e, int j) -> float& { return *(float*)(gbase + (size_t)e * gs0 + (size_t)j * gs1); };
    for (int e = s0 + n_live; e < s1; ++e)
        for (int j = 0; j < 10; ++j) GE(e, j) = 0.0f;
    for (int k = n_live - 1; k >= 0; --k) {
        const int e = s0 + k;
        const int g = I1(entries, e);
        if (k >= PREFETCH) {
            const int gn = I1(entries, e - PREFETCH);
            __builtin_prefetch(pbase + (size_t)gn * ps0);
            __builtin_prefetch(pbase + (size_t)gn * ps0 + 9 * ps1);  // a 40-byte row can cross a cache line
            __builtin_prefetch((const char*)pthr.data + (size_t)gn * pthr.strides[0]);
        }
        const float mx = P(g, 0), my = P(g, 1), ca = P(g, 2), cb = P(g, 3), cc = P(g, 4), op = P(g, 5);
        const float cr = P(g, 6), cg = P(g, 7), cbl = P(g, 8), z = P(g, 9);
        const float lo = F1(pthr, g);
        const float det_q = ca * cc - cb * cb;
        alignas(64) float v[10][16];
        for (int m = 0; m < 10; ++m)
            for (int j = 0; j < 16; ++j) v[m][j] = 0.0f;
        if (lo < 0.0f && det_q > 0.0f) {
            for_blocks(mx, my, ca, cb, cc, det_q, lo, [&](int base, float fx0, int bc, const float* dyl,
                                                      const float* cdy, const float* bdy) {
                float* __restrict__ TRb = TR + base;
                float* __restrict__ BHb = BH + base;
                const float* __restrict__ GRb = GR + base;
                const float* __restrict__ GGb = GG + base;
                const float* __restrict__ GBb = GB + base;
                const float* __restrict__ GDb = GD + base;
                const int* __restrict__ Lb = LAST + base;
                for (int l = 0; l < 16; ++l) {
                    const float dx = fx0 + (float)(4 * bc + (l & 3));
                    const float dy = dyl[l];
                    const float power = -0.5f * ca * dx * dx + cdy[l] - bdy[l] * dx;
                    const float G = fexp(power);
                    const float raw = op * G;
                    const float a = raw < 0.99f ? raw : 0.99f;
                    const bool m = (k < Lb[l]) & (power <= 0.0f) & (power >= lo) & (a >= ALPHA_MIN);
                    const float inv_1ma = 1.0f / (1.0f - a);
                    const float Tn = TRb[l] * inv_1ma;
                    TRb[l] = m ? Tn : TRb[l];
                    const float w = m ? a * Tn : 0.0f;
                    const float gr = GRb[l], gg = GGb[l], gb = GBb[l], gd = GDb[l];
                    const float front = gr * cr + gg * cg + gb * cbl + gd * z;
                    const float bh = BHb[l];
                    BHb[l] = bh + w * front;
                    const float g_a = (m & (raw < 0.99f)) ? Tn * front - bh * inv_1ma : 0.0f;
                    v[6][l] += w * gr;
                    v[7][l] += w * gg;
                    v[8][l] += w * gb;
                    v[9][l] += w * gd;
                    v[5][l] += g_a * G;
                    const float g_p = g_a * a;
                    const float gx = g_p * dx, gy = g_p * dy;
                    v[0][l] += gx;  // moments of g_p over the pixels: combined into the five gradients below
                    v[1][l] += gy;
                    v[2][l] += gx * dx;
                    v[3][l] += gx * dy;
                    v[4][l] += gy * dy;
                }
            });
        }
        // the lanes' sums as a tree of whole-vector adds (16 -> 8 -> 4 lanes, then 2 + 2), in registers
        float sum[10];
        for (int m = 0; m < 10; ++m) {
            f16v x;
            __builtin_memcpy(&x, v[m], sizeof(x));
            const f8v h = __builtin_shufflevector(x, x, 0, 1, 2, 3, 4, 5, 6, 7)
                        + __builtin_shufflevector(x, x, 8, 9, 10, 11, 12, 13, 14, 15);
            const f4v q = __builtin_shufflevector(h, h, 0, 1, 2, 3) + __builtin_shufflevector(h, h, 4, 5, 6, 7);
            sum[m] = (q[0] + q[2]) + (q[1] + q[3]);
        }
        // d power / d (mx, my, a, b, c) from the moments sum g_p dx, g_p dy, g_p dx^2, g_p dx dy, g_p dy^2
        GE(e, 0) = ca * sum[0] + cb * sum[1];
        GE(e, 1) = cc * sum[1] + cb * sum[0];
        GE(e, 2) = -0.5f * sum[2];
        GE(e, 3) = -sum[3];
        GE(e, 4) = -0.5f * sum[4];
        for (int m = 5; m < 10; ++m) GE(e, m) = sum[m];
    }
"""


@wp.func_native(_FORWARD)
def _tile_forward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
                  entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int,
                  tiles_x: int, t: int, color: wp.array(dtype=float), depth: wp.array(dtype=float),
                  dnorm: wp.array(dtype=float), alpha: wp.array(dtype=float), t_final: wp.array(dtype=float),
                  last: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
    ...


@wp.func_native(_BACKWARD)
def _tile_backward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
                   entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int,
                   tiles_x: int, t: int, t_final: wp.array(dtype=float), dnorm: wp.array(dtype=float),
                   last: wp.array(dtype=wp.int32), g_color: wp.array(dtype=float), g_depth: wp.array(dtype=float),
                   g_dnorm: wp.array(dtype=float), g_alpha: wp.array(dtype=float), g_entry: wp.array2d(dtype=float)):
    ...


@wp.kernel
def forward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
            entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
            tile_offset: int, color: wp.array(dtype=float), depth: wp.array(dtype=float),
            dnorm: wp.array(dtype=float), alpha: wp.array(dtype=float), t_final: wp.array(dtype=float),
            last: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
    _tile_forward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, wp.tid() + tile_offset, color, depth,
                  dnorm, alpha, t_final, last, hits)


@wp.kernel
def backward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
             entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
             tile_offset: int, t_final: wp.array(dtype=float), dnorm: wp.array(dtype=float),
             last: wp.array(dtype=wp.int32), g_color: wp.array(dtype=float), g_depth: wp.array(dtype=float),
             g_dnorm: wp.array(dtype=float), g_alpha: wp.array(dtype=float), g_entry: wp.array2d(dtype=float)):
    _tile_backward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, wp.tid() + tile_offset, t_final,
                   dnorm, last, g_color, g_depth, g_dnorm, g_alpha, g_entry)
