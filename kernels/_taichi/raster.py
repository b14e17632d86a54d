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


@ti.kernel
def _forward(packed: _f2, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32, tiles_x: ti.i32,
             n_tiles: ti.i32, color: _f3, depth: _f2, t_final: _f2, last: _i2, hits: _i1):
    ti.loop_config(block_dim=1)  # one tile per task: tiles differ wildly in cost
    for t in range(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for e in range(s0, s1):
            hits[e] = 0
        for lp in range(TILE * TILE):
            py = ty * TILE + lp // TILE
            px = tx * TILE + lp % TILE
            if px < width and py < height:
                fx = ti.cast(px, ti.f32)
                fy = ti.cast(py, ti.f32)
                T = 1.0
                cr = 0.0
                cg = 0.0
                cb = 0.0
                d = 0.0
                n = 0
                for e in range(s0, s1):
                    g = entries[e]
                    dx = fx - packed[g, 0]
                    dy = fy - packed[g, 1]
                    power = -0.5 * (packed[g, 2] * dx * dx + packed[g, 4] * dy * dy) - packed[g, 3] * dx * dy
                    if power <= 0.0:
                        a = ti.min(0.99, packed[g, 5] * ti.exp(power))
                        if a >= ALPHA_MIN:
                            test_T = T * (1.0 - a)
                            if test_T < 1e-4:
                                break
                            w = a * T
                            cr += w * packed[g, 6]
                            cg += w * packed[g, 7]
                            cb += w * packed[g, 8]
                            d += w * packed[g, 9]
                            T = test_T
                            n = e - s0 + 1
                            hits[e] += 1
                color[py, px, 0] = cr + T * bg[0]
                color[py, px, 1] = cg + T * bg[1]
                color[py, px, 2] = cb + T * bg[2]
                depth[py, px] = d
                t_final[py, px] = T
                last[py, px] = n


@ti.kernel
def _backward(packed: _f2, tile_start: _i1, entries: _i1, bg: _f1, width: ti.i32, height: ti.i32, tiles_x: ti.i32,
              n_tiles: ti.i32, t_final: _f2, last: _i2, g_color: _f3, g_depth: _f2, g_alpha: _f2, g_entry: _f2):
    ti.loop_config(block_dim=1)
    for t in range(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s0 = tile_start[t]
        s1 = tile_start[t + 1]
        for e in range(s0, s1):
            for k in ti.static(range(10)):
                g_entry[e, k] = 0.0
        for lp in range(TILE * TILE):
            py = ty * TILE + lp // TILE
            px = tx * TILE + lp % TILE
            if px < width and py < height:
                fx = ti.cast(px, ti.f32)
                fy = ti.cast(py, ti.f32)
                TN = t_final[py, px]
                T = TN
                gr = g_color[py, px, 0]
                gg = g_color[py, px, 1]
                gb = g_color[py, px, 2]
                gd = g_depth[py, px]
                # what lies behind Gaussian k, seen through it: background and alpha terms start the sums
                behind = (gr * bg[0] + gg * bg[1] + gb * bg[2] - g_alpha[py, px]) * TN
                n = last[py, px]
                for i in range(n):
                    e = s0 + n - 1 - i
                    g = entries[e]
                    dx = fx - packed[g, 0]
                    dy = fy - packed[g, 1]
                    ca = packed[g, 2]
                    cb_ = packed[g, 3]
                    cc = packed[g, 4]
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb_ * dx * dy
                    if power <= 0.0:
                        G = ti.exp(power)
                        raw = packed[g, 5] * G
                        a = ti.min(0.99, raw)
                        if a >= ALPHA_MIN:
                            T = T / (1.0 - a)
                            w = a * T
                            front = gr * packed[g, 6] + gg * packed[g, 7] + gb * packed[g, 8] + gd * packed[g, 9]
                            g_a = T * front - behind / (1.0 - a)
                            behind += w * front
                            g_entry[e, 6] += w * gr
                            g_entry[e, 7] += w * gg
                            g_entry[e, 8] += w * gb
                            g_entry[e, 9] += w * gd
                            if raw < 0.99:
                                g_entry[e, 5] += g_a * G
                                g_p = g_a * a
                                g_entry[e, 0] += g_p * (ca * dx + cb_ * dy)
                                g_entry[e, 1] += g_p * (cc * dy + cb_ * dx)
                                g_entry[e, 2] -= 0.5 * g_p * dx * dx
                                g_entry[e, 3] -= g_p * dx * dy
                                g_entry[e, 4] -= 0.5 * g_p * dy * dy


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


def render_forward(packed, tile_start, entries, bg, width, height, color, depth, t_final, last, hits, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    _forward(_nonempty(packed), tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, color, depth,
             t_final, last, hits)
    _sync(device)


def render_backward(packed, tile_start, entries, bg, width, height, t_final, last, g_color, g_depth, g_alpha, g_entry,
                    device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    _backward(_nonempty(packed), tile_start, entries, bg, width, height, tiles_x, tiles_x * tiles_y, t_final, last,
              g_color, g_depth, g_alpha, g_entry)
    _sync(device)
