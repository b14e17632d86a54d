"""Taichi kernels of the Gaussian rasteriser: tile binning, forward compositing, reverse compositing.

The same design as kernels/_warp/raster.py: one loop iteration owns a 16x16 tile, its pixels and its entries in
the tile list, so the backward writes per-entry gradients without atomics. Taichi parallelises the outermost
loop over all CPU cores by itself. The layout of `packed` rows is kernels.raster.PACKED:
mean2d x, y, conic a, b, c, opacity, r, g, b, z.
"""


import taichi as ti
import torch

TILE = 16
ALPHA_MIN = 1.0 / 255.0

_f2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
_f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
_f3 = ti.types.ndarray(dtype=ti.f32, ndim=3)
_i1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_i2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


@ti.kernel
def _bin(rect: _i2, m: ti.i32, tiles_x: ti.i32, n_tiles: ti.i32, tile_start: _i1, entries: _i1):
    # Serial counting sort of (tile, depth-rank) pairs: visiting Gaussians in depth order keeps each tile's list
    # front to back. tile_start doubles as the write cursor and is shifted back at the end.
    ti.loop_config(serialize=True)
    for t in range(n_tiles + 1):
        tile_start[t] = 0
    ti.loop_config(serialize=True)
    for g in range(m):
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                tile_start[ty * tiles_x + tx + 1] += 1
    ti.loop_config(serialize=True)
    for t in range(n_tiles):
        tile_start[t + 1] += tile_start[t]
    ti.loop_config(serialize=True)
    for g in range(m):
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                t = ty * tiles_x + tx
                entries[tile_start[t]] = g
                tile_start[t] += 1
    ti.loop_config(serialize=True)
    for i in range(n_tiles):
        t = n_tiles - i
        tile_start[t] = tile_start[t - 1]
    tile_start[0] = 0


@ti.func
def _pixel_box(mx, my, ca, cb, cc, lg, x0, y0, x1, y1):
    # Pixels of the tile [x0, x1) x [y0, y1) where alpha can reach 1/255 (see kernels/_warp/raster.py); returns
    # (bx0, by0, bx1, by1) inclusive, empty when bx1 < bx0.
    det_q = ca * cc - cb * cb
    out = ti.math.ivec4(0, 0, -1, -1)
    if lg > 0.0 and det_q > 0.0:
        ex = ti.sqrt(2.0 * lg * cc / det_q) + 1.0
        ey = ti.sqrt(2.0 * lg * ca / det_q) + 1.0
        out = ti.math.ivec4(ti.cast(ti.max(ti.cast(x0, ti.f32), ti.ceil(mx - ex)), ti.i32),
                            ti.cast(ti.max(ti.cast(y0, ti.f32), ti.ceil(my - ey)), ti.i32),
                            ti.cast(ti.min(ti.cast(x1 - 1, ti.f32), ti.floor(mx + ex)), ti.i32),
                            ti.cast(ti.min(ti.cast(y1 - 1, ti.f32), ti.floor(my + ey)), ti.i32))
    return out


@ti.kernel
def _forward(packed: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
             tiles_x: ti.i32, n_tiles: ti.i32, color: _f3, depth: _f2, t_final: _f2, last: _i2, hits: _i1):
    # Entry-outer per tile, as the Warp kernel: t_final holds the running transmittance, negated once done.
    ti.loop_config(block_dim=1)  # one tile per task: tiles differ wildly in cost
    for t in range(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * TILE
        y0 = ty * TILE
        x1 = ti.min(x0 + TILE, width)
        y1 = ti.min(y0 + TILE, height)
        for py in range(y0, y1):
            for px in range(x0, x1):
                t_final[py, px] = 1.0
                color[py, px, 0] = 0.0
                color[py, px, 1] = 0.0
                color[py, px, 2] = 0.0
                depth[py, px] = 0.0
                last[py, px] = 0
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for e in range(s0, s1):
            g = entries[e]
            mx = packed[g, 0]
            my = packed[g, 1]
            ca = packed[g, 2]
            cb = packed[g, 3]
            cc = packed[g, 4]
            op = packed[g, 5]
            lo = pthr[g]
            box = _pixel_box(mx, my, ca, cb, cc, -lo, x0, y0, x1, y1)
            count = 0
            for py in range(box[1], box[3] + 1):
                dy = ti.cast(py, ti.f32) - my
                for px in range(box[0], box[2] + 1):
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
                                else:
                                    w = a * T
                                    color[py, px, 0] += w * packed[g, 6]
                                    color[py, px, 1] += w * packed[g, 7]
                                    color[py, px, 2] += w * packed[g, 8]
                                    depth[py, px] += w * packed[g, 9]
                                    t_final[py, px] = test_T
                                    last[py, px] = e - s0 + 1
                                    count += 1
            hits[e] = count
        for py in range(y0, y1):
            for px in range(x0, x1):
                T = ti.abs(t_final[py, px])
                t_final[py, px] = T
                color[py, px, 0] += T * bg[0]
                color[py, px, 1] += T * bg[1]
                color[py, px, 2] += T * bg[2]


@ti.kernel
def _backward(packed: _f2, pthr: _f1, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32,
              tiles_x: ti.i32, n_tiles: ti.i32, t_final: _f2, last: _i2, g_color: _f3, g_depth: _f2, g_alpha: _f2,
              t_run: _f2, behind: _f2, g_entry: _f2):
    # Reverse compositing, entry-outer from the back of each tile list (see the Warp kernel for the algebra).
    ti.loop_config(block_dim=1)
    for t in range(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * TILE
        y0 = ty * TILE
        x1 = ti.min(x0 + TILE, width)
        y1 = ti.min(y0 + TILE, height)
        for py in range(y0, y1):
            for px in range(x0, x1):
                TN = t_final[py, px]
                t_run[py, px] = TN
                behind[py, px] = (g_color[py, px, 0] * bg[0] + g_color[py, px, 1] * bg[1]
                                  + g_color[py, px, 2] * bg[2] - g_alpha[py, px]) * TN
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for i in range(s1 - s0):
            e = s1 - 1 - i
            k = e - s0
            g = entries[e]
            mx = packed[g, 0]
            my = packed[g, 1]
            ca = packed[g, 2]
            cb = packed[g, 3]
            cc = packed[g, 4]
            op = packed[g, 5]
            cr = packed[g, 6]
            cg = packed[g, 7]
            cbl = packed[g, 8]
            z = packed[g, 9]
            lo = pthr[g]
            box = _pixel_box(mx, my, ca, cb, cc, -lo, x0, y0, x1, y1)
            v = ti.Vector([0.0] * 10)  # d/d(mean2d x, y, conic a, b, c, opacity, r, g, b, z)
            for py in range(box[1], box[3] + 1):
                dy = ti.cast(py, ti.f32) - my
                for px in range(box[0], box[2] + 1):
                    if k < last[py, px]:
                        dx = ti.cast(px, ti.f32) - mx
                        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power <= 0.0 and power >= lo:
                            G = ti.exp(power)
                            raw = op * G
                            a = ti.min(0.99, raw)
                            if a >= ALPHA_MIN:
                                T = t_run[py, px] / (1.0 - a)
                                t_run[py, px] = T
                                w = a * T
                                gr = g_color[py, px, 0]
                                gg = g_color[py, px, 1]
                                gb = g_color[py, px, 2]
                                gd = g_depth[py, px]
                                front = gr * cr + gg * cg + gb * cbl + gd * z
                                bh = behind[py, px]
                                g_a = T * front - bh / (1.0 - a)
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


def _sync(device: str) -> None:
    if device == "cuda":
        ti.sync()


def bin_tiles(rect: torch.Tensor, tiles_x: int, tiles_y: int, tile_start: torch.Tensor, entries: torch.Tensor,
              device: str) -> None:
    """rect [M, 4] int32 tile ranges of depth-sorted Gaussians -> tile_start [T+1], entries [E] (filled here)."""
    m = rect.shape[0]
    rect_arg = rect if m else torch.zeros((1, 4), dtype=torch.int32, device=rect.device)  # Taichi rejects 0-size
    _bin(rect_arg, m, tiles_x, tiles_x * tiles_y, tile_start, entries)
    _sync(device)


def _nonempty(packed: torch.Tensor) -> torch.Tensor:
    return packed if packed.shape[0] else torch.zeros((1, 10), dtype=torch.float32, device=packed.device)


def _nonempty1(x: torch.Tensor) -> torch.Tensor:
    return x if x.shape[0] else torch.zeros(1, dtype=torch.float32, device=x.device)


def render_forward(packed, pthr, tile_start, entries, bg, width, height, color, depth, t_final, last, hits, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    _forward(_nonempty(packed), _nonempty1(pthr), tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, color, depth,
             t_final, last, hits)
    _sync(device)


def render_backward(packed, pthr, tile_start, entries, bg, width, height, t_final, last, g_color, g_depth, g_alpha,
                    t_run, behind, g_entry, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    _backward(_nonempty(packed), _nonempty1(pthr), tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, t_final, last,
              g_color, g_depth, g_alpha, t_run, behind, g_entry)
    _sync(device)
