"""CPU compositing kernels of the Taichi rasteriser, written so that LLVM turns them into vector code.

kernels/_taichi/raster.py composites one pixel at a time, which Taichi's CPU code generator emits as scalar code
(~3.5x slower than Warp's vector snippet, kernels/_warp/raster_cpu.py). Taichi has no native-code escape, so these
kernels are ordinary Taichi code in the one shape its LLVM pipeline vectorises (read in the optimised IR,
`ti.init(print_kernel_llvm_ir_optimized=True)`):

- per-pixel state lives in registers: one `ti.Vector` of 16 lanes (LANES) per quantity, loop-carried across the
  tile's entries, so each is one <16 x float> PHI that LLVM's SLP vectoriser takes as a seed: the per-pixel work
  becomes 16-lane arithmetic, branch-free (masks and `ti.select`).
  (Per-pixel state in local arrays indexed at run time, as in the Warp snippet, stays scalar: Taichi indexes them
  with 32-bit arithmetic without no-wrap flags, so LLVM cannot prove the lanes consecutive.)
- forward: the 16 lanes are a 4x4-pixel block. A first pass over the tile's entries stages each one's projected
  row into contiguous scratch and appends it to the list of every block its ellipse's bounding box reaches; each
  block then composites its own list. At 320x240 with 60k Gaussians an entry reaches 3.95 blocks of 16 pixels
  against 5.85 tile rows of 16 (the row layout before, which also tested every entry of the tile in every row):
  forward 25.8 -> 20.4 ms CPU on one mapping step's inputs. The lanes' offsets in the block are read from an
  array (LANE_XY): written as constants, x and y have four distinct values each, LLVM folds the repeats and the
  SLP vectoriser splits the arithmetic into 4- and 2-lane pieces (the forward was no faster than the rows).
- backward: a tile row per vector, two rows at a time (32 lanes), every entry of the tile tested per row pair.
  4x4 blocks with per-block lists were measured too and were no faster there (50.6 against 50.8 ms): the ten
  per-entry sums are horizontal sums per visit, and a block layout visits an entry more often (3.95 blocks
  against 3.27 row pairs); Taichi cannot keep an entry's sums in registers across its blocks the way the Warp
  snippet does, as the blocks are the outer loop here. Blocks of 4 rows x 8 columns (2.63 per entry, two vectors)
  were 5 % faster (48.5 against 50.9 ms), too little for a second staging scheme; entry-outer with the blocks'
  state in ndarrays of 16-lane vectors, as the Warp snippet, was 2.4x slower (their loads stay scalar), and with
  the 16 blocks' state as values of a static block index (`ti.static` unrolled) LLVM was still compiling after
  10 minutes and 7 GB.
- exp is the Warp snippet's polynomial (Cody-Waite, Cephes' coefficients), with the exponent rounded by an
  integer conversion (x <= 0): with `ti.floor` there the forward was 1.5x slower (same harness; not pinned down).
- Taichi compiles for the host CPU (AVX-512 zmm code here; `ti.init(print_kernel_asm=True)` shows it), but the
  per-entry sums, the gradient writes and the per-lane loads stay scalar, and the backward's two rows of state
  spill to the stack.
- backward: the ten per-Gaussian gradient sums of a row pair are horizontal sums. LLVM vectorises a horizontal
  sum only where it feeds a PHI, so each pair's sums are carried to the next iteration of the entry loop and
  added into `g_entry` there (and after the loop). Written directly, the whole gradient tail stayed scalar (~1.6x
  slower than this).
- backward: a first pass over the tile's entries stages each one's projected row (and the rows of the tile its
  ellipse reaches, packed in one int) into contiguous scratch, so the row loops read it sequentially.

The rules and outputs are those of kernels/_taichi/raster.py and the twin (kernels.reference): power =
-0.5 (a dx^2 + c dy^2) - b dx dy in [lo, 0], alpha = min(0.99, opacity exp(power)) >= 1/255, a pixel stops before
the Gaussian that would take its transmittance below 1e-4; a block (forward) or row whose pixels have all
stopped leaves the entry loop. Results differ from the scalar kernels by float32 rounding only (the polynomial exp, relative error 1.2e-7,
and the order of the gradient sums). CPU only: GPU archs keep the scalar kernels (one tile per thread there).
"""

import taichi as ti

from .launch import SPREAD
from .raster import ALPHA_MIN, DEPTH_EPS, TILE, _entry_conic, _f1, _f2, _f3, _i1, _i2, _reverse_start, _rows

LANES = TILE  # one vector: a tile row (backward), a 4x4-pixel block (forward)
BLOCKS = 16  # 4x4-pixel blocks of a tile
NO_ROWS = -1  # staged code of an entry whose ellipse box misses its tile (or that is culled)
LANE_XY = [j & 3 for j in range(LANES)] + [j >> 2 for j in range(LANES)]  # a block's lanes: column, then row


@ti.func
def _exp(x):
    # exp of each lane, for x in [-20, 0] (clamped): x = n ln2 + r, exp(r) = 1 + r + r^2 P(r) (as the Warp snippet)
    x = ti.min(ti.max(x, -20.0), 0.0)
    ni = ti.cast(x * 1.44269504088896341 - 0.5, ti.i32)  # x <= 0: truncation rounds to nearest
    n = ti.cast(ni, ti.f32)
    r = x - n * 0.693145751953125
    r = r - n * 1.42860682030941723e-06
    r2 = r * r
    pa = 5.0000001201e-1 + 1.6666665459e-1 * r
    pb = 4.1665795894e-2 + 8.3334519073e-3 * r
    pc = 1.3981999507e-3 + 1.9875691500e-4 * r
    p = (1.0 + r) + r2 * (pa + r2 * (pb + r2 * pc))
    scale = ti.Vector([0.0] * LANES)
    for j in ti.static(range(LANES)):
        scale[j] = ti.bit_cast((ni[j] + 127) << 23, ti.f32)
    return p * scale


@ti.func
def _tile(t, tiles_x, width, height):
    # first pixel and size of tile t (cut by the image edges)
    ty = t // tiles_x
    x0 = (t - ty * tiles_x) * TILE
    y0 = ty * TILE
    return x0, y0, ti.min(x0 + TILE, width) - x0, ti.min(y0 + TILE, height) - y0


@ti.func
def _stage(proj: ti.template(), pthr: ti.template(), entries: ti.template(), rows: ti.template(),
           rec: ti.template(), e, y0, nh):
    # rows[e] = first | last << 8 (tile rows the ellipse d^T Q d <= 2 lg reaches, lg widened as the scalar
    # kernels widen it) or NO_ROWS; rec[e] = mean x, y, conic a, b, c, opacity, lo, r, g, b, z
    g, lo, ca, cb, cc, det_q = _entry_conic(proj, pthr, entries, e)
    code = NO_ROWS
    if lo < 0.0 and det_q > 0.0:
        my = proj[g, 1]
        span = _rows(my, ca, det_q, -1.01 * lo + 0.01, y0, y0 + nh)
        if span[0] <= span[1]:
            code = (span[0] - y0) | ((span[1] - y0) << 8)
            _stage_rec(proj, rec, e, g, proj[g, 0], my, ca, cb, cc, lo)
    rows[e] = code


@ti.func
def _stage_rec(proj: ti.template(), rec: ti.template(), e, g, mx, my, ca, cb, cc, lo):
    # rec[e] = mean x, y, conic a, b, c, opacity, lo, r, g, b, z of entry e's Gaussian g
    rec[e, 0] = mx
    rec[e, 1] = my
    rec[e, 2] = ca
    rec[e, 3] = cb
    rec[e, 4] = cc
    rec[e, 5] = proj[g, 5]
    rec[e, 6] = lo
    for j in ti.static(range(4)):
        rec[e, 7 + j] = proj[g, 6 + j]


@ti.func
def _stage_tile(proj: ti.template(), pthr: ti.template(), tile_start: ti.template(), entries: ti.template(), width,
                height, tiles_x, t, rows: ti.template(), rec: ti.template()):
    # tile t's first pixel, size and entry range [s0, s1), its entries staged (_stage)
    x0, y0, nw, nh = _tile(t, tiles_x, width, height)
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    for e in range(s0, s1):
        _stage(proj, pthr, entries, rows, rec, e, y0, nh)
    return x0, y0, nw, nh, s0, s1


@ti.func
def _stage_blocks(proj: ti.template(), pthr: ti.template(), tile_start: ti.template(), entries: ti.template(),
                  width, height, tiles_x, t, rec: ti.template(), blist: ti.template(), bcount: ti.template()):
    # tile t's first pixel, size and entry range [s0, s1); each entry's projected row staged in rec[e] (mean x, y,
    # conic a, b, c, opacity, lo, r, g, b, z) and appended, in list order, to the list of every 4x4 block of the
    # tile its ellipse's bounding box reaches: block b's list is blist[16 s0 + b (s1 - s0) + i], i < bcount[16 t + b]
    x0, y0, nw, nh = _tile(t, tiles_x, width, height)
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    n = s1 - s0
    for b in range(BLOCKS):
        bcount[BLOCKS * t + b] = 0
    for e in range(s0, s1):
        g, lo, ca, cb, cc, det_q = _entry_conic(proj, pthr, entries, e)
        if lo < 0.0 and det_q > 0.0:
            mx = proj[g, 0]
            my = proj[g, 1]
            lg = -1.01 * lo + 0.01
            ry = _rows(my, ca, det_q, lg, y0, y0 + nh)
            cx = _rows(mx, cc, det_q, lg, x0, x0 + nw)  # the same bound along x: the columns
            if ry[0] <= ry[1] and cx[0] <= cx[1]:
                _stage_rec(proj, rec, e, g, mx, my, ca, cb, cc, lo)
                for br in range((ry[0] - y0) >> 2, ((ry[1] - y0) >> 2) + 1):
                    for bc in range((cx[0] - x0) >> 2, ((cx[1] - x0) >> 2) + 1):
                        b = 4 * br + bc
                        c = bcount[BLOCKS * t + b]
                        blist[BLOCKS * s0 + b * n + c] = e
                        bcount[BLOCKS * t + b] = c + 1
    return x0, y0, nw, nh, s0, n


@ti.func
def _block_lanes(lane_xy: ti.template(), x0, y0, b):
    # pixel x, y of each lane of block b (as float32) and the lanes' column and row in the tile. The lanes' offsets
    # in the block are read from lane_xy (0 1 2 3 0 1 2 3 ... then 0 0 0 0 1 1 1 1 ...), not written as constants:
    # folded, each has only 4 distinct values and LLVM's SLP vectoriser splits the 16-lane arithmetic that uses them
    col = ti.Vector([0] * LANES)
    row = ti.Vector([0] * LANES)
    for j in ti.static(range(LANES)):
        col[j] = 4 * (b & 3) + lane_xy[j]
        row[j] = 4 * (b >> 2) + lane_xy[LANES + j]
    return ti.cast(col + x0, ti.f32), ti.cast(row + y0, ti.f32), col, row


@ti.func
def _forward_tile(proj: ti.template(), pthr: ti.template(), tile_start: ti.template(), entries: ti.template(),
                  bg: ti.template(), width, height, tiles_x, t, color: ti.template(), depth: ti.template(),
                  dnorm: ti.template(), alpha: ti.template(), t_final: ti.template(), last: ti.template(),
                  hits: ti.template(), rec: ti.template(), blist: ti.template(), bcount: ti.template(),
                  lane_xy: ti.template(), count: ti.template()):
    x0, y0, nw, nh, s0, n = _stage_blocks(proj, pthr, tile_start, entries, width, height, tiles_x, t, rec,
                                          blist, bcount)
    if ti.static(count):
        for e in range(s0, s0 + n):
            hits[e] = 0
    for b in range(BLOCKS):
        if 4 * (b & 3) < nw and 4 * (b >> 2) < nh:
            pxv, pyv, col, row = _block_lanes(lane_xy, x0, y0, b)
            inside = (col < nw) & (row < nh)
            T = ti.select(inside, 1.0, 0.0)  # lanes outside the image never composite
            cr = ti.Vector([0.0] * LANES)
            cg = ti.Vector([0.0] * LANES)
            cb = ti.Vector([0.0] * LANES)
            dd = ti.Vector([0.0] * LANES)
            la = ti.Vector([0] * LANES)
            n_live = ti.select(inside, 1, 0).sum()
            base = BLOCKS * s0 + b * n
            for i in range(bcount[BLOCKS * t + b]):
                e = blist[base + i]
                dy = pyv - rec[e, 1]
                dx = pxv - rec[e, 0]
                power = (-0.5 * rec[e, 2]) * dx * dx + (-0.5 * rec[e, 4] * dy * dy) - (rec[e, 3] * dy) * dx
                a = ti.min(0.99, rec[e, 5] * _exp(power))
                ok = (T > 0.0) & (power <= 0.0) & (power >= rec[e, 6]) & (a >= ALPHA_MIN)
                test_t = T * (1.0 - a)
                stop = ok & (test_t < 1e-4)
                comp = ok & (test_t >= 1e-4)
                w = ti.select(comp, a * T, 0.0)
                cr += w * rec[e, 7]
                cg += w * rec[e, 8]
                cb += w * rec[e, 9]
                dd += w * rec[e, 10]
                T = ti.select(stop, -T, ti.select(comp, test_t, T))  # negated: stopped
                la = ti.select(comp, e - s0 + 1, la)
                if ti.static(count):
                    hits[e] += ti.select(comp, 1, 0).sum()
                if stop.any():
                    n_live -= ti.select(stop, 1, 0).sum()
                    if n_live <= 0:
                        break
            for j in ti.static(range(LANES)):
                if inside[j]:
                    px = x0 + col[j]
                    py = y0 + row[j]
                    tj = ti.abs(T[j])
                    aj = 1.0 - tj
                    t_final[py, px] = tj
                    alpha[py, px] = aj
                    color[py, px, 0] = cr[j] + tj * bg[0]
                    color[py, px, 1] = cg[j] + tj * bg[1]
                    color[py, px, 2] = cb[j] + tj * bg[2]
                    depth[py, px] = dd[j]
                    last[py, px] = la[j]
                    dn = 0.0
                    if aj > DEPTH_EPS:
                        dn = dd[j] / aj
                    dnorm[py, px] = dn


@ti.kernel
def forward(proj: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
            tiles_x: ti.i32, n_tiles: ti.i32, color: _f3, depth: _f2, dnorm: _f2, alpha: _f2, t_final: _f2,
            last: _i2, hits: _i1, rec: _f2, blist: _i1, bcount: _i1, lane_xy: _i1, count: ti.template()):
    # count: write hits (pixels each entry composited); that store in the entry loop makes the forward ~1.7x slower
    for it in range(n_tiles * SPREAD):  # one tile per SPREAD iterations (kernels/_taichi/launch.py)
        if it % SPREAD == 0:
            _forward_tile(proj, pthr, tile_start, entries, bg, width, height, tiles_x, it // SPREAD, color, depth,
                          dnorm, alpha, t_final, last, hits, rec, blist, bcount, lane_xy, count)


@ti.func
def _flush(g_entry: ti.template(), e, ca, cb, cc, s_dx, s_dy, s_dx2, s_dxdy, s_dy2, s_op, s_r, s_g, s_b, s_d):
    # a row pair's sums into entry e's gradient (mean2d x, y, conic a, b, c, opacity, r, g, b, z): d/dmean and
    # d/dconic from the sums of g_p dx, g_p dy, g_p dx^2, g_p dx dy and g_p dy^2
    g_entry[e, 0] += ca * s_dx + cb * s_dy
    g_entry[e, 1] += cc * s_dy + cb * s_dx
    g_entry[e, 2] -= 0.5 * s_dx2
    g_entry[e, 3] -= s_dxdy
    g_entry[e, 4] -= 0.5 * s_dy2
    g_entry[e, 5] += s_op
    g_entry[e, 6] += s_r
    g_entry[e, 7] += s_g
    g_entry[e, 8] += s_b
    g_entry[e, 9] += s_d


@ti.func
def _load_row(t_final: ti.template(), dnorm: ti.template(), last: ti.template(), g_color: ti.template(),
              g_depth: ti.template(), g_dnorm: ti.template(), g_alpha: ti.template(), bg: ti.template(), py, x0, nw,
              ok):
    # one tile row's per-pixel state for the reverse pass (ok False: a row below the image, every lane inactive)
    T = ti.Vector([0.0] * LANES)
    bh = ti.Vector([0.0] * LANES)
    gr = ti.Vector([0.0] * LANES)
    gg = ti.Vector([0.0] * LANES)
    gb = ti.Vector([0.0] * LANES)
    gd = ti.Vector([0.0] * LANES)
    la = ti.Vector([0] * LANES)
    if ok:
        for j in ti.static(range(LANES)):
            if j < nw:
                px = x0 + j
                T[j], gd[j], bh[j] = _reverse_start(t_final, dnorm, g_color, g_depth, g_dnorm, g_alpha, bg, py, px)
                gr[j] = g_color[py, px, 0]
                gg[j] = g_color[py, px, 1]
                gb[j] = g_color[py, px, 2]
                la[j] = last[py, px]
    return T, bh, gr, gg, gb, gd, la


@ti.func
def _backward_tile(proj: ti.template(), pthr: ti.template(), tile_start: ti.template(), entries: ti.template(),
                   bg: ti.template(), width, height, tiles_x, t, t_final: ti.template(), dnorm: ti.template(),
                   last: ti.template(), g_color: ti.template(), g_depth: ti.template(), g_dnorm: ti.template(),
                   g_alpha: ti.template(), g_entry: ti.template(), rows: ti.template(), rec: ti.template()):
    # Reverse compositing (see kernels/_taichi/raster.py for the algebra) two tile rows at a time: T recovers
    # T_k = T_{k+1} / (1 - a_k) from the back, behind accumulates (dL/dC . colour + dL/dD depth) of everything
    # behind entry k. A row pair shares the entry's loads, its ten sums and its gradient write (one row at a time
    # was 1.3-1.4x slower).
    x0, y0, nw, nh, s0, s1 = _stage_tile(proj, pthr, tile_start, entries, width, height, tiles_x, t, rows, rec)
    for e in range(s0, s1):
        for j in ti.static(range(10)):
            g_entry[e, j] = 0.0
    lane = ti.Vector([j for j in range(LANES)])
    pxv = ti.cast(lane + x0, ti.f32)
    for q in range((nh + 1) // 2):
        r0 = 2 * q
        r1 = r0 + 1
        T0, bh0, gr0, gg0, gb0, gd0, la0 = _load_row(t_final, dnorm, last, g_color, g_depth, g_dnorm, g_alpha, bg,
                                                     y0 + r0, x0, nw, True)
        T1, bh1, gr1, gg1, gb1, gd1, la1 = _load_row(t_final, dnorm, last, g_color, g_depth, g_dnorm, g_alpha, bg,
                                                     y0 + r1, x0, nw, r1 < nh)
        n_live = ti.max(la0.max(), la1.max())
        # the previous entry's sums, carried to the next iteration (see the module docstring)
        pe = -1
        p_ca, p_cb, p_cc = 0.0, 0.0, 0.0
        s_dx, s_dy, s_dx2, s_dxdy, s_dy2 = 0.0, 0.0, 0.0, 0.0, 0.0
        s_op, s_r, s_g, s_b, s_d = 0.0, 0.0, 0.0, 0.0, 0.0
        pyf0 = ti.cast(y0 + r0, ti.f32)
        for i in range(n_live):
            k = n_live - 1 - i
            e = s0 + k
            code = rows[e]
            if code >= 0 and (code & 255) <= r1 and r0 <= (code >> 8):
                in0 = (code & 255) <= r0
                in1 = r1 <= (code >> 8)
                ca = rec[e, 2]
                cb_ = rec[e, 3]
                cc = rec[e, 4]
                op = rec[e, 5]
                lo = rec[e, 6]
                dx = pxv - rec[e, 0]
                dy0 = pyf0 - rec[e, 1]
                dy1 = dy0 + 1.0
                pxx = (-0.5 * ca) * dx * dx
                p0 = pxx + (-0.5 * cc * dy0 * dy0) - (cb_ * dy0) * dx
                p1 = pxx + (-0.5 * cc * dy1 * dy1) - (cb_ * dy1) * dx
                G0 = _exp(p0)
                G1 = _exp(p1)
                raw0 = op * G0
                raw1 = op * G1
                a0 = ti.min(0.99, raw0)
                a1 = ti.min(0.99, raw1)
                act0 = (la0 > k) & (p0 <= 0.0) & (p0 >= lo) & (a0 >= ALPHA_MIN) & in0
                act1 = (la1 > k) & (p1 <= 0.0) & (p1 >= lo) & (a1 >= ALPHA_MIN) & in1
                if act0.any() or act1.any():  # no lane composited this entry: nothing to add
                    if pe >= 0:
                        _flush(g_entry, pe, p_ca, p_cb, p_cc, s_dx, s_dy, s_dx2, s_dxdy, s_dy2, s_op, s_r, s_g, s_b,
                               s_d)
                    cr = rec[e, 7]
                    cg = rec[e, 8]
                    cbl = rec[e, 9]
                    z = rec[e, 10]
                    i0 = 1.0 / (1.0 - a0)
                    i1 = 1.0 / (1.0 - a1)
                    tk0 = T0 * i0
                    tk1 = T1 * i1
                    T0 = ti.select(act0, tk0, T0)
                    T1 = ti.select(act1, tk1, T1)
                    w0 = ti.select(act0, a0 * tk0, 0.0)
                    w1 = ti.select(act1, a1 * tk1, 0.0)
                    f0 = gr0 * cr + gg0 * cg + gb0 * cbl + gd0 * z
                    f1 = gr1 * cr + gg1 * cg + gb1 * cbl + gd1 * z
                    # alpha clamped at 0.99: no gradient through it
                    ga0 = ti.select(act0 & (raw0 < 0.99), tk0 * f0 - bh0 * i0, 0.0)
                    ga1 = ti.select(act1 & (raw1 < 0.99), tk1 * f1 - bh1 * i1, 0.0)
                    bh0 += w0 * f0
                    bh1 += w1 * f1
                    gp0 = ga0 * a0
                    gp1 = ga1 * a1
                    gpdy0 = gp0 * dy0
                    gpdy1 = gp1 * dy1
                    gpdx = gp0 * dx + gp1 * dx
                    gpdy = gpdy0 + gpdy1
                    s_dx = gpdx.sum()
                    s_dy = gpdy.sum()
                    s_dx2 = (gpdx * dx).sum()
                    s_dxdy = (gpdy * dx).sum()
                    s_dy2 = (gpdy0 * dy0 + gpdy1 * dy1).sum()
                    s_op = (ga0 * G0 + ga1 * G1).sum()
                    s_r = (w0 * gr0 + w1 * gr1).sum()
                    s_g = (w0 * gg0 + w1 * gg1).sum()
                    s_b = (w0 * gb0 + w1 * gb1).sum()
                    s_d = (w0 * gd0 + w1 * gd1).sum()
                    pe = e
                    p_ca, p_cb, p_cc = ca, cb_, cc
        if pe >= 0:
            _flush(g_entry, pe, p_ca, p_cb, p_cc, s_dx, s_dy, s_dx2, s_dxdy, s_dy2, s_op, s_r, s_g, s_b, s_d)


@ti.kernel
def backward(proj: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
             tiles_x: ti.i32, n_tiles: ti.i32, t_final: _f2, dnorm: _f2, last: _i2, g_color: _f3, g_depth: _f2,
             g_dnorm: _f2, g_alpha: _f2, g_entry: _f2, rows: _i1, rec: _f2):
    for it in range(n_tiles * SPREAD):  # one tile per SPREAD iterations (kernels/_taichi/launch.py)
        if it % SPREAD == 0:
            _backward_tile(proj, pthr, tile_start, entries, bg, width, height, tiles_x, it // SPREAD, t_final,
                           dnorm, last, g_color, g_depth, g_dnorm, g_alpha, g_entry, rows, rec)
