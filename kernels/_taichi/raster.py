"""Taichi kernels of the Gaussian rasteriser: forward compositing and reverse compositing over per-tile lists.

The same design as kernels/_warp/raster.py (read its docstring): one loop iteration owns a 16x16 tile, its pixels
and its entries (Gaussian indices, front to back, from kernels/_taichi/sort.py), so the backward writes per-entry
gradients without atomics; each Gaussian visits only the per-row spans of its alpha >= 1/255 ellipse. Taichi
parallelises the outermost loop over all CPU cores by itself (spread over SPREAD iterations a tile on the CPU:
kernels/_taichi/launch.py). Projected rows use kernels.raster.PACKED: mean2d x, y, conic a, b, c, opacity, r, g,
b, z.

On the CPU the compositing runs kernels/_taichi/raster_cpu.py's row-vector kernels instead (same rules; ~3.5x
faster forward and ~2x backward at 640x480 / 50k); these one-tile-per-thread kernels serve the GPU archs (CUDA,
Vulkan) and, with CPU_COMPOSITE = "scalar", the CPU as perf's taichi-scalar peer.
"""


import taichi as ti
import torch

from .launch import SPREAD, on_cpu

TILE = 16
ALPHA_MIN = 1.0 / 255.0
DEPTH_EPS = 1e-6

_f2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
_f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_f3 = ti.types.ndarray(dtype=ti.f32, ndim=3)
_i1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_i2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


@ti.func
def _entry_conic(proj: ti.template(), pthr: ti.template(), entries: ti.template(), e):
    # tile entry e's Gaussian, its exp() skip threshold lo and conic a, b, c with its determinant; it composites
    # nothing unless lo < 0 and det_q > 0
    g = entries[e]
    ca = proj[g, 2]
    cb = proj[g, 3]
    cc = proj[g, 4]
    return g, pthr[g], ca, cb, cc, ca * cc - cb * cb


@ti.func
def _rows(my, ca, det_q, lg, y0, y1):
    # Rows of the tile [y0, y1) the ellipse d^T Q d <= 2 lg can reach (lg already widened); (first, last).
    ey = ti.sqrt(2.0 * lg * ca / det_q)
    return ti.math.ivec2(ti.cast(ti.math.clamp(ti.ceil(my - ey), ti.cast(y0, ti.f32), ti.cast(y1, ti.f32)), ti.i32),
                         ti.cast(ti.math.clamp(ti.floor(my + ey), ti.cast(y0 - 1, ti.f32), ti.cast(y1 - 1, ti.f32)),
                                 ti.i32))


@ti.func
def _span(mx, dy, cb, inv_ca, det_q, lgm2ca, x0, x1):
    # Pixels of one row where alpha can reach 1/255 (see kernels/_warp/raster.py); (first, last) inclusive.
    disc = lgm2ca - det_q * dy * dy
    out = ti.math.ivec2(x0, x0 - 1)
    if disc >= 0.0:
        h = ti.sqrt(disc) * inv_ca
        xc = mx - cb * dy * inv_ca
        out = ti.math.ivec2(
            ti.cast(ti.math.clamp(ti.ceil(xc - h), ti.cast(x0, ti.f32), ti.cast(x1, ti.f32)), ti.i32),
            ti.cast(ti.math.clamp(ti.floor(xc + h), ti.cast(x0 - 1, ti.f32), ti.cast(x1 - 1, ti.f32)), ti.i32))
    return out


@ti.func
def _tile_box(t, tiles_x, width, height):
    # Pixels [x0, x1) x [y0, y1) of tile t (row-major over tiles_x tiles per row), clipped to the image.
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * TILE
    y0 = ty * TILE
    return ti.math.ivec4(x0, y0, ti.min(x0 + TILE, width), ti.min(y0 + TILE, height))


@ti.kernel
def _forward(proj: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
             tiles_x: ti.i32, n_tiles: ti.i32, color: _f3, depth: _f2, dnorm: _f2, alpha: _f2, t_final: _f2,
             last: _i2, hits: _i1):
    # Entry-outer per tile, as the Warp kernel: t_final holds the running transmittance, negated once done.
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: one tile per SPREAD iterations (kernels/_taichi/launch.py)
    for it in range(n_tiles * sp):
        if it % sp != 0:
            continue
        t = it // sp
        box = _tile_box(t, tiles_x, width, height)
        x0, y0, x1, y1 = box[0], box[1], box[2], box[3]
        for py in range(y0, y1):
            for px in range(x0, x1):
                t_final[py, px] = 1.0
                color[py, px, 0] = 0.0
                color[py, px, 1] = 0.0
                color[py, px, 2] = 0.0
                depth[py, px] = 0.0
                last[py, px] = 0
        npix = (x1 - x0) * (y1 - y0)
        done = 0
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for e in range(s0, s1):
            count = 0
            g, lo, ca, cb, cc, det_q = _entry_conic(proj, pthr, entries, e)
            if done < npix and lo < 0.0 and det_q > 0.0:
                mx = proj[g, 0]
                my = proj[g, 1]
                op = proj[g, 5]
                inv_ca = 1.0 / ca
                lgm2ca = 2.0 * ca * (-1.01 * lo + 0.01)
                rows = _rows(my, ca, det_q, -1.01 * lo + 0.01, y0, y1)
                for py in range(rows[0], rows[1] + 1):
                    dy = ti.cast(py, ti.f32) - my
                    span = _span(mx, dy, cb, inv_ca, det_q, lgm2ca, x0, x1)
                    for px in range(span[0], span[1] + 1):
                        T = t_final[py, px]
                        if T > 0.0:
                            dx = ti.cast(px, ti.f32) - mx
                            power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                            if power <= 0.0 and power >= lo:
                                a = ti.min(0.99, op * ti.exp(power))
                                if a >= ALPHA_MIN:
                                    test_T = T * (1.0 - a)
                                    if test_T < 1e-4:
                                        t_final[py, px] = -T
                                        done += 1
                                    else:
                                        w = a * T
                                        color[py, px, 0] = color[py, px, 0] + w * proj[g, 6]
                                        color[py, px, 1] = color[py, px, 1] + w * proj[g, 7]
                                        color[py, px, 2] = color[py, px, 2] + w * proj[g, 8]
                                        depth[py, px] = depth[py, px] + w * proj[g, 9]
                                        t_final[py, px] = test_T
                                        last[py, px] = e - s0 + 1
                                        count += 1
            hits[e] = count
        for py in range(y0, y1):
            for px in range(x0, x1):
                T = ti.abs(t_final[py, px])
                t_final[py, px] = T
                a = 1.0 - T
                alpha[py, px] = a
                color[py, px, 0] = color[py, px, 0] + T * bg[0]
                color[py, px, 1] = color[py, px, 1] + T * bg[1]
                color[py, px, 2] = color[py, px, 2] + T * bg[2]
                dn = 0.0
                if a > DEPTH_EPS:
                    dn = depth[py, px] / a
                dnorm[py, px] = dn


@ti.func
def _reverse_start(t_final: ti.template(), dnorm: ti.template(), g_color: ti.template(), g_depth: ti.template(),
                   g_dnorm: ti.template(), g_alpha: ti.template(), bg: ti.template(), py, px):
    # a pixel's start of the reverse pass: its final transmittance, its depth gradient with depth_normalised =
    # depth / alpha folded in, and the term of everything behind the last entry (background, alpha)
    tn = t_final[py, px]
    a_px = 1.0 - tn
    gd = g_depth[py, px]
    ga = g_alpha[py, px]
    if a_px > DEPTH_EPS:
        gn = g_dnorm[py, px] / a_px
        gd += gn
        ga -= gn * dnorm[py, px]
    bh = (g_color[py, px, 0] * bg[0] + g_color[py, px, 1] * bg[1] + g_color[py, px, 2] * bg[2] - ga) * tn
    return tn, gd, bh


@ti.kernel
def _backward(proj: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
              tiles_x: ti.i32, n_tiles: ti.i32, t_final: _f2, dnorm: _f2, last: _i2, g_color: _f3, g_depth: _f2,
              g_dnorm: _f2, g_alpha: _f2, t_run: _f2, behind: _f2, g_dep: _f2, g_entry: _f2):
    # Reverse compositing, entry-outer from the back of each tile list (see the Warp kernel for the algebra).
    sp = ti.static(SPREAD if on_cpu() else 1)  # CPU: one tile per SPREAD iterations (kernels/_taichi/launch.py)
    for it in range(n_tiles * sp):
        if it % sp != 0:
            continue
        t = it // sp
        box = _tile_box(t, tiles_x, width, height)
        x0, y0, x1, y1 = box[0], box[1], box[2], box[3]
        n_live = 0
        for py in range(y0, y1):
            for px in range(x0, x1):
                TN, gd, bh = _reverse_start(t_final, dnorm, g_color, g_depth, g_dnorm, g_alpha, bg, py, px)
                g_dep[py, px] = gd
                t_run[py, px] = TN
                behind[py, px] = bh
                n_live = ti.max(n_live, last[py, px])
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for e in range(s0 + n_live, s1):
            for j in ti.static(range(10)):
                g_entry[e, j] = 0.0
        for i in range(n_live):
            k = n_live - 1 - i
            e = s0 + k
            g = entries[e]
            mx = proj[g, 0]
            my = proj[g, 1]
            ca = proj[g, 2]
            cb = proj[g, 3]
            cc = proj[g, 4]
            op = proj[g, 5]
            cr = proj[g, 6]
            cg = proj[g, 7]
            cbl = proj[g, 8]
            z = proj[g, 9]
            lo = pthr[g]
            det_q = ca * cc - cb * cb
            v = ti.Vector([0.0] * 10)  # d/d(mean2d x, y, conic a, b, c, opacity, r, g, b, z)
            if lo < 0.0 and det_q > 0.0:
                inv_ca = 1.0 / ca
                lgm2ca = 2.0 * ca * (-1.01 * lo + 0.01)
                rows = _rows(my, ca, det_q, -1.01 * lo + 0.01, y0, y1)
                for py in range(rows[0], rows[1] + 1):
                    dy = ti.cast(py, ti.f32) - my
                    span = _span(mx, dy, cb, inv_ca, det_q, lgm2ca, x0, x1)
                    for px in range(span[0], span[1] + 1):
                        if k < last[py, px]:
                            dx = ti.cast(px, ti.f32) - mx
                            power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                            if power <= 0.0 and power >= lo:
                                G = ti.exp(power)
                                raw = op * G
                                a = ti.min(0.99, raw)
                                if a >= ALPHA_MIN:
                                    inv_1ma = 1.0 / (1.0 - a)
                                    T = t_run[py, px] * inv_1ma
                                    t_run[py, px] = T
                                    w = a * T
                                    gr = g_color[py, px, 0]
                                    gg = g_color[py, px, 1]
                                    gb = g_color[py, px, 2]
                                    gd = g_dep[py, px]
                                    front = gr * cr + gg * cg + gb * cbl + gd * z
                                    bh = behind[py, px]
                                    g_a = T * front - bh * inv_1ma
                                    behind[py, px] = bh + w * front
                                    v[6] += w * gr
                                    v[7] += w * gg
                                    v[8] += w * gb
                                    v[9] += w * gd
                                    if raw < 0.99:
                                        v[5] += g_a * G
                                        g_p = g_a * a
                                        v[0] += g_p * (ca * dx + cb * dy)
                                        v[1] += g_p * (cc * dy + cb * dx)
                                        v[2] -= 0.5 * g_p * dx * dx
                                        v[3] -= g_p * dx * dy
                                        v[4] -= 0.5 * g_p * dy * dy
            for j in ti.static(range(10)):
                g_entry[e, j] = v[j]


# "vector": the CPU composites with kernels/_taichi/raster_cpu.py; "scalar": with the kernels above
CPU_COMPOSITE = "vector"


def _sync(device: str) -> None:
    if device == "cuda":
        ti.sync()


def _vector(device: str):
    """kernels/_taichi/raster_cpu.py when the CPU composites with it, else None."""
    if device == "cpu" and CPU_COMPOSITE == "vector" and on_cpu():
        from . import raster_cpu  # imports this module's constants

        return raster_cpu
    return None


def _staging(tile_start):
    """Per-entry scratch of the vector backward (CPU tensors): packed tile rows and the staged projected rows, one
    per tile entry in use (the entry buffer itself is larger: its capacity)."""
    n = max(int(tile_start[-1]), 1)
    return (torch.empty((n,), dtype=torch.int32), torch.empty((n, 11), dtype=torch.float32))


_LANE_XY: list = []


def _block_staging(tile_start, n_tiles: int):
    """Scratch of the vector forward (CPU tensors): the staged projected rows, the 4x4 blocks' entry lists (room
    for every entry in each of its tile's 16 blocks), the lists' lengths, and the lanes' offsets in a block."""
    from .raster_cpu import BLOCKS, LANE_XY

    if not _LANE_XY:
        _LANE_XY.append(torch.tensor(LANE_XY, dtype=torch.int32))
    n = max(int(tile_start[-1]), 1)
    return (torch.empty((n, 11), dtype=torch.float32), torch.empty((BLOCKS * n,), dtype=torch.int32),
            torch.empty((BLOCKS * n_tiles,), dtype=torch.int32), _LANE_XY[0])


def render_forward(proj, pthr, tile_start, entries, bg, width, height, color, depth, dnorm, alpha, t_final, last,
                   hits, device, count_hits: bool = True) -> None:
    """count_hits False: `hits` may be left unwritten (the CPU's vector kernel skips them; nothing reads them)."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    cpu = _vector(device)
    if cpu is not None:
        cpu.forward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, color, depth,
                     dnorm, alpha, t_final, last, hits, *_block_staging(tile_start, tiles_x * tiles_y),
                     bool(count_hits))
        return
    _forward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, color, depth, dnorm,
             alpha, t_final, last, hits)
    _sync(device)


def render_backward(proj, pthr, tile_start, entries, bg, width, height, t_final, dnorm, last, g_color, g_depth,
                    g_dnorm, g_alpha, g_entry, device) -> None:
    """Image gradients may be strided (expanded); Taichi takes contiguous arrays."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    g_color, g_depth, g_dnorm, g_alpha = (g.contiguous() for g in (g_color, g_depth, g_dnorm, g_alpha))
    cpu = _vector(device)
    if cpu is not None:  # its per-pixel scratch lives in registers
        cpu.backward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, t_final, dnorm,
                      last, g_color, g_depth, g_dnorm, g_alpha, g_entry, *_staging(tile_start))
        return
    t_run, behind, g_dep = (torch.empty_like(t_final) for _ in range(3))  # the per-pixel scratch of the reverse pass
    _backward(proj, pthr, tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, t_final, dnorm, last,
              g_color, g_depth, g_dnorm, g_alpha, t_run, behind, g_dep, g_entry)
    _sync(device)
