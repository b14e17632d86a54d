"""Warp kernels of the Gaussian rasteriser: tile binning, forward compositing, reverse compositing.

Work is split per 16x16 tile: one kernel thread owns a tile, its pixels and its entries in the tile list, so the
backward writes per-entry gradients without atomics and the caller reduces them. Warp's CPU backend runs one
launch on one OS thread, but the launch releases the GIL (ctypes), so on the CPU the tiles are cut into chunks
launched from a small thread pool — race-free because chunks share no tile. On CUDA one launch covers all tiles.
The pool has os.cpu_count() workers unless the environment variable SWARMSPLAT_WARP_CPU_THREADS says otherwise.
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


@wp.func
def _pixel_box(mx: float, my: float, ca: float, cb: float, cc: float, lg: float, x0: int, y0: int, x1: int, y1: int):
    # Pixels of the tile [x0, x1) x [y0, y1) where alpha can reach 1/255: the ellipse d^T Q d <= 2 ln(255 o) has
    # half-extents sqrt(2 ln(255 o) (Q^-1)_xx), ...; one pixel of margin against rounding (the exact per-pixel test
    # still decides). Returns (bx0, by0, bx1, by1) inclusive; empty when bx1 < bx0.
    det_q = ca * cc - cb * cb
    out = wp.vec4i(0, 0, -1, -1)
    if lg > 0.0 and det_q > 0.0:
        ex = wp.sqrt(2.0 * lg * cc / det_q) + 1.0
        ey = wp.sqrt(2.0 * lg * ca / det_q) + 1.0
        out = wp.vec4i(int(wp.max(float(x0), wp.ceil(mx - ex))), int(wp.max(float(y0), wp.ceil(my - ey))),
                       int(wp.min(float(x1 - 1), wp.floor(mx + ex))), int(wp.min(float(y1 - 1), wp.floor(my + ey))))
    return out


@wp.kernel
def _forward(packed: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
             entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
             tile_offset: int, color: wp.array3d(dtype=float), depth: wp.array2d(dtype=float),
             t_final: wp.array2d(dtype=float), last: wp.array2d(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
    # Entry-outer order: each Gaussian of the tile (front to back) visits only the pixels of its alpha >= 1/255
    # box; the per-pixel state lives in the output images (L1-resident for one tile). t_final holds the running
    # transmittance, negated once the pixel is done (the next Gaussian would take it below 1e-4).
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * TILE
    y0 = ty * TILE
    x1 = wp.min(x0 + TILE, width)
    y1 = wp.min(y0 + TILE, height)
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
        count = int(0)
        for py in range(box[1], box[3] + 1):
            dy = float(py) - my
            for px in range(box[0], box[2] + 1):
                T = t_final[py, px]
                if T > 0.0:
                    dx = float(px) - mx
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power <= 0.0 and power >= lo:
                        a = wp.min(0.99, op * wp.exp(power))
                        if a >= ALPHA_MIN:
                            test_T = T * (1.0 - a)
                            if test_T < 1e-4:
                                t_final[py, px] = -T
                            else:
                                w = a * T
                                color[py, px, 0] = color[py, px, 0] + w * packed[g, 6]
                                color[py, px, 1] = color[py, px, 1] + w * packed[g, 7]
                                color[py, px, 2] = color[py, px, 2] + w * packed[g, 8]
                                depth[py, px] = depth[py, px] + w * packed[g, 9]
                                t_final[py, px] = test_T
                                last[py, px] = e - s0 + 1
                                count += 1
        hits[e] = count
    for py in range(y0, y1):
        for px in range(x0, x1):
            T = wp.abs(t_final[py, px])
            t_final[py, px] = T
            color[py, px, 0] = color[py, px, 0] + T * bg[0]
            color[py, px, 1] = color[py, px, 1] + T * bg[1]
            color[py, px, 2] = color[py, px, 2] + T * bg[2]


@wp.kernel
def _backward(packed: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
              entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
              tile_offset: int, t_final: wp.array2d(dtype=float), last: wp.array2d(dtype=wp.int32),
              g_color: wp.array3d(dtype=float), g_depth: wp.array2d(dtype=float), g_alpha: wp.array2d(dtype=float),
              t_run: wp.array2d(dtype=float), behind: wp.array2d(dtype=float), g_entry: wp.array2d(dtype=float)):
    # Reverse compositing, entry-outer from the back of the tile list: t_run recovers T_k = T_{k+1} / (1 - a_k),
    # behind accumulates (dL/dC . colour + dL/dD depth) of everything behind Gaussian k, background and alpha
    # terms included. Each entry's gradient is summed in registers over its pixels and written once.
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * TILE
    y0 = ty * TILE
    x1 = wp.min(x0 + TILE, width)
    y1 = wp.min(y0 + TILE, height)
    for py in range(y0, y1):
        for px in range(x0, x1):
            TN = t_final[py, px]
            t_run[py, px] = TN
            behind[py, px] = (g_color[py, px, 0] * bg[0] + g_color[py, px, 1] * bg[1] + g_color[py, px, 2] * bg[2]
                              - g_alpha[py, px]) * TN
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
        v_mx = float(0.0)
        v_my = float(0.0)
        v_a = float(0.0)
        v_b = float(0.0)
        v_c = float(0.0)
        v_o = float(0.0)
        v_r = float(0.0)
        v_g = float(0.0)
        v_bl = float(0.0)
        v_z = float(0.0)
        for py in range(box[1], box[3] + 1):
            dy = float(py) - my
            for px in range(box[0], box[2] + 1):
                if k < last[py, px]:
                    dx = float(px) - mx
                    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power <= 0.0 and power >= lo:
                        G = wp.exp(power)
                        raw = op * G
                        a = wp.min(0.99, raw)
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
                            v_r += w * gr
                            v_g += w * gg
                            v_bl += w * gb
                            v_z += w * gd
                            if raw < 0.99:
                                v_o += g_a * G
                                g_p = g_a * a
                                v_mx += g_p * (ca * dx + cb * dy)
                                v_my += g_p * (cc * dy + cb * dx)
                                v_a -= 0.5 * g_p * dx * dx
                                v_b -= g_p * dx * dy
                                v_c -= 0.5 * g_p * dy * dy
        g_entry[e, 0] = v_mx
        g_entry[e, 1] = v_my
        g_entry[e, 2] = v_a
        g_entry[e, 3] = v_b
        g_entry[e, 4] = v_c
        g_entry[e, 5] = v_o
        g_entry[e, 6] = v_r
        g_entry[e, 7] = v_g
        g_entry[e, 8] = v_bl
        g_entry[e, 9] = v_z


def to_warp(t: torch.Tensor, dtype=None):
    # detached and without Warp-side grads: the hand-written backward owns the gradients
    return wp.from_torch(t.detach(), dtype=dtype, requires_grad=False)


_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_loaded: set = set()


def _workers() -> int:
    return max(1, int(os.environ.get("SWARMSPLAT_WARP_CPU_THREADS", os.cpu_count() or 1)))


def launch_chunked(kernel, n: int, inputs: list, offset_pos: int, device: str) -> None:
    """Launch `kernel` over n items whose first index is inputs[offset_pos]; on the CPU in contiguous chunks from
    a thread pool (see the module docstring). Chunks must not write to shared memory."""
    global _pool
    workers = _workers() if device == "cpu" else 1
    if workers == 1 or n < 2 or (kernel.key, device) not in _loaded:
        # the first launch compiles and loads the module: do it on this thread, once
        wp.launch(kernel, dim=n, inputs=_with_offset(inputs, offset_pos, 0), device=device)
        _loaded.add((kernel.key, device))
        return
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="warp-raster")
    n_chunks = min(n, 4 * workers)  # more chunks than workers evens out dense and empty regions
    bounds = [n * i // n_chunks for i in range(n_chunks + 1)]
    futures = [
        _pool.submit(wp.launch, kernel, dim=bounds[i + 1] - bounds[i],
                     inputs=_with_offset(inputs, offset_pos, bounds[i]), device=device)
        for i in range(n_chunks) if bounds[i + 1] > bounds[i]
    ]
    for f in futures:
        f.result()


def _with_offset(inputs: list, pos: int, offset: int) -> list:
    out = list(inputs)
    out[pos] = offset
    return out


_OFFSET_POS = 8  # index of `tile_offset` in both tile kernels' argument lists


def bin_tiles(rect: torch.Tensor, tiles_x: int, tiles_y: int, tile_start: torch.Tensor, entries: torch.Tensor,
              device: str) -> None:
    """rect [M, 4] int32 tile ranges of depth-sorted Gaussians -> tile_start [T+1], entries [E] (filled here)."""
    rect_w = to_warp(rect.reshape(-1, 4), dtype=wp.int32) if rect.shape[0] else wp.zeros((0, 4), dtype=wp.int32, device=device)
    wp.launch(_bin, dim=1, inputs=[rect_w, tiles_x, tiles_x * tiles_y, to_warp(tile_start), to_warp(entries)],
              device=device)


def render_forward(packed, pthr, tile_start, entries, bg, width, height, color, depth, t_final, last, hits, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    packed_w = to_warp(packed) if packed.shape[0] else wp.zeros((0, 10), dtype=float, device=device)
    inputs = [packed_w, to_warp(pthr), to_warp(tile_start), to_warp(entries), to_warp(bg), width, height, tiles_x,
              0, to_warp(color), to_warp(depth), to_warp(t_final), to_warp(last),
              to_warp(hits)]
    launch_chunked(_forward, tiles_x * tiles_y, inputs, _OFFSET_POS, device)
    if device == "cuda":
        wp.synchronize_device(device)


def render_backward(packed, pthr, tile_start, entries, bg, width, height, t_final, last, g_color, g_depth, g_alpha,
                    t_run, behind, g_entry, device) -> None:
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    inputs = [to_warp(packed), to_warp(pthr), to_warp(tile_start), to_warp(entries), to_warp(bg), width, height,
              tiles_x, 0, to_warp(t_final), to_warp(last), to_warp(g_color), to_warp(g_depth),
              to_warp(g_alpha), to_warp(t_run), to_warp(behind), to_warp(g_entry)]
    launch_chunked(_backward, tiles_x * tiles_y, inputs, _OFFSET_POS, device)
    if device == "cuda":
        wp.synchronize_device(device)
