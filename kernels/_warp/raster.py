"""Warp kernels of the Gaussian rasteriser: tile binning, forward compositing, reverse compositing.

Work is split per 16x16 tile: one kernel thread owns a tile, its pixels and its entries in the tile list, so the
backward writes per-entry gradients without atomics and the caller reduces them. Warp's CPU backend runs one
launch on one OS thread, but the launch releases the GIL (ctypes), so on the CPU the tiles are cut into chunks
launched from a small thread pool — race-free because chunks share no tile. On CUDA one launch covers all tiles.
The layout of `packed` rows is kernels.raster.PACKED: mean2d x, y, conic a, b, c, opacity, r, g, b, z.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

# backward is hand-written (no Warp adjoints); no unrolling of the 16x16 pixel loops (256 copies compile for minutes)
wp.set_module_options({"enable_backward": False, "max_unroll": 0})

TILE = 16
ALPHA_MIN = 1.0 / 255.0


@wp.kernel
def _bin(rect: wp.array2d(dtype=wp.int32), tiles_x: int, n_tiles: int, tile_start: wp.array(dtype=wp.int32),
         entries: wp.array(dtype=wp.int32)):
    # One thread: a counting sort of (tile, depth-rank) pairs; visiting Gaussians in depth order keeps each
    # tile's list front to back, which a parallel sort would have to restore with (tile, depth) keys.
    m = rect.shape[0]
    for t in range(n_tiles + 1):
        tile_start[t] = 0
    for g in range(m):
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                tile_start[ty * tiles_x + tx + 1] = tile_start[ty * tiles_x + tx + 1] + 1
    for t in range(n_tiles):
        tile_start[t + 1] = tile_start[t + 1] + tile_start[t]
    for g in range(m):
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                t = ty * tiles_x + tx
                # tile_start[t] is used as the write cursor and restored by the shift below
                entries[tile_start[t]] = g
                tile_start[t] = tile_start[t] + 1
    for i in range(n_tiles):
        t = n_tiles - i
        tile_start[t] = tile_start[t - 1]
    tile_start[0] = 0


@wp.kernel
def _forward(packed: wp.array2d(dtype=float), tile_start: wp.array(dtype=wp.int32), entries: wp.array(dtype=wp.int32),
             bg: wp.array(dtype=float), width: int, height: int, tiles_x: int, tile_offset: int,
             color: wp.array3d(dtype=float), depth: wp.array2d(dtype=float), t_final: wp.array2d(dtype=float),
             last: wp.array2d(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    for e in range(s0, s1):
        hits[e] = 0
    for ly in range(TILE):
        py = ty * TILE + ly
        for lx in range(TILE):
            px = tx * TILE + lx
            if px < width and py < height:
                fx = float(px)
                fy = float(py)
                T = float(1.0)
                cr = float(0.0)
                cg = float(0.0)
                cb = float(0.0)
                d = float(0.0)
                n = int(0)
                for e in range(s0, s1):
                    g = entries[e]
                    dx = fx - packed[g, 0]
                    dy = fy - packed[g, 1]
                    power = -0.5 * (packed[g, 2] * dx * dx + packed[g, 4] * dy * dy) - packed[g, 3] * dx * dy
                    if power <= 0.0:
                        a = wp.min(0.99, packed[g, 5] * wp.exp(power))
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
                            hits[e] = hits[e] + 1
                color[py, px, 0] = cr + T * bg[0]
                color[py, px, 1] = cg + T * bg[1]
                color[py, px, 2] = cb + T * bg[2]
                depth[py, px] = d
                t_final[py, px] = T
                last[py, px] = n


@wp.kernel
def _backward(packed: wp.array2d(dtype=float), tile_start: wp.array(dtype=wp.int32), entries: wp.array(dtype=wp.int32),
              bg: wp.array(dtype=float), width: int, height: int, tiles_x: int, tile_offset: int,
              t_final: wp.array2d(dtype=float), last: wp.array2d(dtype=wp.int32), g_color: wp.array3d(dtype=float),
              g_depth: wp.array2d(dtype=float), g_alpha: wp.array2d(dtype=float), g_entry: wp.array2d(dtype=float)):
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    for e in range(s0, s1):
        for k in range(10):
            g_entry[e, k] = 0.0
    for ly in range(TILE):
        py = ty * TILE + ly
        for lx in range(TILE):
            px = tx * TILE + lx
            if px < width and py < height:
                fx = float(px)
                fy = float(py)
                TN = t_final[py, px]
                T = float(TN)
                gr = g_color[py, px, 0]
                gg = g_color[py, px, 1]
                gb = g_color[py, px, 2]
                gd = g_depth[py, px]
                # what lies behind Gaussian k, seen through it: background and alpha terms start the sums
                behind = float(0.0) + (gr * bg[0] + gg * bg[1] + gb * bg[2] - g_alpha[py, px]) * TN
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
                        G = wp.exp(power)
                        raw = packed[g, 5] * G
                        a = wp.min(0.99, raw)
                        if a >= ALPHA_MIN:
                            T = T / (1.0 - a)
                            w = a * T
                            front = gr * packed[g, 6] + gg * packed[g, 7] + gb * packed[g, 8] + gd * packed[g, 9]
                            g_a = T * front - behind / (1.0 - a)
                            behind += w * front
                            g_entry[e, 6] = g_entry[e, 6] + w * gr
                            g_entry[e, 7] = g_entry[e, 7] + w * gg
                            g_entry[e, 8] = g_entry[e, 8] + w * gb
                            g_entry[e, 9] = g_entry[e, 9] + w * gd
                            if raw < 0.99:
                                g_entry[e, 5] = g_entry[e, 5] + g_a * G
                                g_p = g_a * a
                                g_entry[e, 0] = g_entry[e, 0] + g_p * (ca * dx + cb_ * dy)
                                g_entry[e, 1] = g_entry[e, 1] + g_p * (cc * dy + cb_ * dx)
                                g_entry[e, 2] = g_entry[e, 2] - 0.5 * g_p * dx * dx
                                g_entry[e, 3] = g_entry[e, 3] - g_p * dx * dy
                                g_entry[e, 4] = g_entry[e, 4] - 0.5 * g_p * dy * dy


def _wp(t: torch.Tensor, dtype=None):
    # detached and without Warp-side grads: the hand-written backward owns the gradients
    return wp.from_torch(t.detach(), dtype=dtype, requires_grad=False)


_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_loaded: set = set()


def _workers() -> int:
    return max(1, int(os.environ.get("SWARMSPLAT_WARP_CPU_THREADS", os.cpu_count() or 1)))


def _launch_tiles(kernel, n_tiles: int, inputs: list, device: str) -> None:
    """Launch `kernel` over tiles; on the CPU in contiguous chunks from a thread pool (see module docstring)."""
    global _pool
    workers = _workers() if device == "cpu" else 1
    if workers == 1 or n_tiles < 2 or (kernel.key, device) not in _loaded:
        # the first launch compiles and loads the module: do it on this thread, once
        wp.launch(kernel, dim=n_tiles, inputs=_with_offset(inputs, 0), device=device)
        _loaded.add((kernel.key, device))
        return
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="warp-raster")
    n_chunks = min(n_tiles, 4 * workers)  # more chunks than workers evens out dense and empty regions
    bounds = [n_tiles * i // n_chunks for i in range(n_chunks + 1)]
    futures = [
        _pool.submit(wp.launch, kernel, dim=bounds[i + 1] - bounds[i], inputs=_with_offset(inputs, bounds[i]), device=device)
        for i in range(n_chunks) if bounds[i + 1] > bounds[i]
    ]
    for f in futures:
        f.result()


def _with_offset(inputs: list, offset: int) -> list:
    out = list(inputs)
    out[_OFFSET_POS] = offset
    return out


_OFFSET_POS = 7  # index of `tile_offset` in both tile kernels' argument lists


def bin_tiles(rect: torch.Tensor, tiles_x: int, tiles_y: int, tile_start: torch.Tensor, entries: torch.Tensor,
              device: str) -> None:
    """rect [M, 4] int32 tile ranges of depth-sorted Gaussians -> tile_start [T+1], entries [E] (filled here)."""
    rect_w = _wp(rect.reshape(-1, 4), dtype=wp.int32) if rect.shape[0] else wp.zeros((0, 4), dtype=wp.int32, device=device)
    wp.launch(_bin, dim=1, inputs=[rect_w, tiles_x, tiles_x * tiles_y, _wp(tile_start), _wp(entries)],
              device=device)


def render_forward(packed, tile_start, entries, bg, width, height, color, depth, t_final, last, hits, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    packed_w = _wp(packed) if packed.shape[0] else wp.zeros((0, 10), dtype=float, device=device)
    inputs = [packed_w, _wp(tile_start), _wp(entries), _wp(bg), width, height, tiles_x,
              0, _wp(color), _wp(depth), _wp(t_final), _wp(last),
              _wp(hits)]
    _launch_tiles(_forward, tiles_x * tiles_y, inputs, device)
    if device == "cuda":
        wp.synchronize_device(device)


def render_backward(packed, tile_start, entries, bg, width, height, t_final, last, g_color, g_depth, g_alpha, g_entry,
                    device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    inputs = [_wp(packed), _wp(tile_start), _wp(entries), _wp(bg), width, height,
              tiles_x, 0, _wp(t_final), _wp(last), _wp(g_color), _wp(g_depth),
              _wp(g_alpha), _wp(g_entry)]
    _launch_tiles(_backward, tiles_x * tiles_y, inputs, device)
    if device == "cuda":
        wp.synchronize_device(device)
