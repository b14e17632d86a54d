"""Warp kernels of the Gaussian rasteriser: forward compositing and reverse compositing over per-tile lists.

Work is split per 16x16 tile: one kernel thread owns a tile, its pixels and its entries in the tile list (built by
kernels/_warp/sort.py, front to back, entries hold Gaussian indices into the projected rows), so the backward
writes per-entry gradients without atomics (kernels/_warp/project.py sums them per Gaussian). A Gaussian visits
only the pixels of its alpha >= 1/255 ellipse: per pixel row the exact span of the quadratic, widened by a margin
(the exact per-pixel test of the twin still decides every pair). Warp's CPU backend runs one launch on one OS
thread, but the launch releases the GIL, so on the CPU the tiles are cut into chunks launched from the pool of
kernels/_warp/launch.py — race-free because chunks share no tile. On CUDA one launch covers all tiles.
The layout of the projected rows is kernels.raster.PACKED: mean2d x, y, conic a, b, c, opacity, r, g, b, z.
"""

from __future__ import annotations

import itertools

import torch
import warp as wp

from . import launch as _launch
from . import raster_cpu as _cpu
from .arrays import to_warp, to_warp_1d

# backward is hand-written (no Warp adjoints); no unrolling of the 16x16 pixel loops (256 copies compile for minutes)
wp.set_module_options({"enable_backward": False, "max_unroll": 0})

TILE = 16
ALPHA_MIN = 1.0 / 255.0
DEPTH_EPS = 1e-6


@wp.func
def _rows(my: float, ca: float, det_q: float, lg: float, y0: int, y1: int):
    # Rows of the tile [y0, y1) the ellipse d^T Q d <= 2 lg can reach (lg already widened); (first, last) inclusive.
    ey = wp.sqrt(2.0 * lg * ca / det_q)
    return wp.vec2i(int(wp.clamp(wp.ceil(my - ey), float(y0), float(y1))),
                    int(wp.clamp(wp.floor(my + ey), float(y0 - 1), float(y1 - 1))))


@wp.func
def _span(mx: float, dy: float, cb: float, inv_ca: float, det_q: float, lgm2ca: float, x0: int, x1: int):
    # Pixels of one row where alpha can reach 1/255: roots of 0.5 a dx^2 + b dy dx + 0.5 c dy^2 = lgm with the
    # threshold widened to lgm = 1.01 lg + 0.01 (lgm2ca = 2 a lgm), far above float32 rounding; (first, last).
    disc = lgm2ca - det_q * dy * dy
    out = wp.vec2i(x0, x0 - 1)
    if disc >= 0.0:
        h = wp.sqrt(disc) * inv_ca
        xc = mx - cb * dy * inv_ca
        out = wp.vec2i(int(wp.clamp(wp.ceil(xc - h), float(x0), float(x1))),
                       int(wp.clamp(wp.floor(xc + h), float(x0 - 1), float(x1 - 1))))
    return out


@wp.kernel
def _forward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
             entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
             tile_offset: int, color: wp.array(dtype=float), depth: wp.array(dtype=float),
             dnorm: wp.array(dtype=float), alpha: wp.array(dtype=float), t_final: wp.array(dtype=float),
             last: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
    # Entry-outer order: each Gaussian of the tile (front to back) visits only the pixels of its alpha >= 1/255
    # ellipse; the per-pixel state lives in the output images (L1-resident for one tile). t_final holds the running
    # transmittance, negated once done (the next Gaussian would take it below 1e-4); a tile whose pixels are all
    # done skips the rest of its list.
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * TILE
    y0 = ty * TILE
    x1 = wp.min(x0 + TILE, width)
    y1 = wp.min(y0 + TILE, height)
    for py in range(y0, y1):
        for px in range(x0, x1):
            q = py * width + px
            t_final[q] = 1.0
            color[3 * q + 0] = 0.0
            color[3 * q + 1] = 0.0
            color[3 * q + 2] = 0.0
            depth[q] = 0.0
            last[q] = 0
    npix = (x1 - x0) * (y1 - y0)
    done = int(0)
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    for e in range(s0, s1):
        count = int(0)
        g = entries[e]
        lo = pthr[g]
        ca = proj[g, 2]
        cb = proj[g, 3]
        cc = proj[g, 4]
        det_q = ca * cc - cb * cb
        if done < npix and lo < 0.0 and det_q > 0.0:
            mx = proj[g, 0]
            my = proj[g, 1]
            op = proj[g, 5]
            inv_ca = 1.0 / ca
            lgm2ca = 2.0 * ca * (-1.01 * lo + 0.01)
            rows = _rows(my, ca, det_q, -1.01 * lo + 0.01, y0, y1)
            for py in range(rows[0], rows[1] + 1):
                dy = float(py) - my
                span = _span(mx, dy, cb, inv_ca, det_q, lgm2ca, x0, x1)
                for px in range(span[0], span[1] + 1):
                    q = py * width + px
                    T = t_final[q]
                    if T > 0.0:
                        dx = float(px) - mx
                        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power <= 0.0 and power >= lo:
                            a = wp.min(0.99, op * wp.exp(power))
                            if a >= ALPHA_MIN:
                                test_T = T * (1.0 - a)
                                if test_T < 1e-4:
                                    t_final[q] = -T
                                    done += 1
                                else:
                                    w = a * T
                                    color[3 * q + 0] = color[3 * q + 0] + w * proj[g, 6]
                                    color[3 * q + 1] = color[3 * q + 1] + w * proj[g, 7]
                                    color[3 * q + 2] = color[3 * q + 2] + w * proj[g, 8]
                                    depth[q] = depth[q] + w * proj[g, 9]
                                    t_final[q] = test_T
                                    last[q] = e - s0 + 1
                                    count += 1
        hits[e] = count
    for py in range(y0, y1):
        for px in range(x0, x1):
            q = py * width + px
            T = wp.abs(t_final[q])
            t_final[q] = T
            a = 1.0 - T
            alpha[q] = a
            color[3 * q + 0] = color[3 * q + 0] + T * bg[0]
            color[3 * q + 1] = color[3 * q + 1] + T * bg[1]
            color[3 * q + 2] = color[3 * q + 2] + T * bg[2]
            dn = float(0.0)
            if a > DEPTH_EPS:
                dn = depth[q] / a
            dnorm[q] = dn


@wp.kernel
def _backward(proj: wp.array2d(dtype=float), pthr: wp.array(dtype=float), tile_start: wp.array(dtype=wp.int32),
              entries: wp.array(dtype=wp.int32), bg: wp.array(dtype=float), width: int, height: int, tiles_x: int,
              tile_offset: int, t_final: wp.array(dtype=float), dnorm: wp.array(dtype=float),
              last: wp.array(dtype=wp.int32), g_color: wp.array(dtype=float), g_depth: wp.array(dtype=float),
              g_dnorm: wp.array(dtype=float), g_alpha: wp.array(dtype=float), t_run: wp.array(dtype=float),
              behind: wp.array(dtype=float), g_dep: wp.array(dtype=float), g_entry: wp.array2d(dtype=float)):
    # Reverse compositing, entry-outer from the back of the tile list: t_run recovers T_k = T_{k+1} / (1 - a_k),
    # behind accumulates (dL/dC . colour + dL/dD depth) of everything behind Gaussian k, background and alpha
    # terms included. depth_normalised = depth / alpha folds into the depth and alpha gradients per pixel first.
    # Each entry's gradient is summed in registers over its pixels and written once; entries behind every
    # pixel's last composited one get zeros without a visit.
    t = wp.tid() + tile_offset
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * TILE
    y0 = ty * TILE
    x1 = wp.min(x0 + TILE, width)
    y1 = wp.min(y0 + TILE, height)
    n_live = int(0)
    for py in range(y0, y1):
        for px in range(x0, x1):
            q = py * width + px
            TN = t_final[q]
            a_px = 1.0 - TN
            gd = g_depth[q]
            ga = g_alpha[q]
            if a_px > DEPTH_EPS:
                gn = g_dnorm[q] / a_px
                gd = gd + gn
                ga = ga - gn * dnorm[q]
            g_dep[q] = gd
            t_run[q] = TN
            behind[q] = (g_color[3 * q + 0] * bg[0] + g_color[3 * q + 1] * bg[1] + g_color[3 * q + 2] * bg[2]
                              - ga) * TN
            n_live = wp.max(n_live, last[q])
    s0 = tile_start[t]
    s1 = tile_start[t + 1]
    for e in range(s0 + n_live, s1):
        for j in range(10):
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
        if lo < 0.0 and det_q > 0.0:
            inv_ca = 1.0 / ca
            lgm2ca = 2.0 * ca * (-1.01 * lo + 0.01)
            rows = _rows(my, ca, det_q, -1.01 * lo + 0.01, y0, y1)
            for py in range(rows[0], rows[1] + 1):
                dy = float(py) - my
                span = _span(mx, dy, cb, inv_ca, det_q, lgm2ca, x0, x1)
                for px in range(span[0], span[1] + 1):
                    q = py * width + px
                    if k < last[q]:
                        dx = float(px) - mx
                        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power <= 0.0 and power >= lo:
                            G = wp.exp(power)
                            raw = op * G
                            a = wp.min(0.99, raw)
                            if a >= ALPHA_MIN:
                                inv_1ma = 1.0 / (1.0 - a)
                                T = t_run[q] * inv_1ma
                                t_run[q] = T
                                w = a * T
                                gr = g_color[3 * q + 0]
                                gg = g_color[3 * q + 1]
                                gb = g_color[3 * q + 2]
                                gd = g_dep[q]
                                front = gr * cr + gg * cg + gb * cbl + gd * z
                                bh = behind[q]
                                g_a = T * front - bh * inv_1ma
                                behind[q] = bh + w * front
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


# "vector": the CPU composites with kernels/_warp/raster_cpu.py (same rules, 8-lane vector code, ~4-5x faster);
# "scalar": with the kernels above, one pixel at a time (the CUDA kernels; kept on the CPU as perf/raster.py's peer)
CPU_COMPOSITE = "vector"

CHUNKS_PER_THREAD = 4  # more chunks than threads evens out dense and empty image regions
MIN_SPLIT_WORK = 16384  # estimated pixel visits below which one launch on this thread is cheaper than a hand-off


def launch_tiles(kernel, n_tiles: int, inputs: list, work: int, device: str) -> None:
    """Launch a tile kernel over n_tiles tiles (inputs[_OFFSET_POS] = first tile); on the CPU cut into contiguous
    chunks that this thread and kernels/_warp/launch.py's pool threads take in turn (dense chunks do not leave
    one thread with the rest). The first launch of a kernel compiles its module on this
    thread; `work` (estimated pixel visits) below MIN_SPLIT_WORK runs as one launch."""
    threads = _launch._cpu_threads() if device == "cpu" else 1
    key = (kernel, device)
    if threads == 1 or n_tiles < 2 or work < MIN_SPLIT_WORK or key not in _launch._LOADED:
        args = list(inputs)
        args[_OFFSET_POS] = 0
        _launch.run(kernel, n_tiles, args, device)
        return
    n_chunks = min(n_tiles, CHUNKS_PER_THREAD * threads)
    cuts = [n_tiles * k // n_chunks for k in range(n_chunks + 1)]

    def part(k: int) -> None:
        args = list(inputs)
        args[_OFFSET_POS] = cuts[k]
        _launch.run(kernel, cuts[k + 1] - cuts[k], args, device)

    chunk = itertools.count()  # chunks are taken in turn by this thread and the pool's (next() holds the GIL)

    def worker() -> None:
        for k in iter(lambda: next(chunk), None):
            if k >= n_chunks:
                return
            part(k)

    pool = _launch._pool(max(1, threads - 1))
    futures = [pool.submit(worker) for _ in range(threads - 1)]
    worker()
    for f in futures:
        f.result()


def _flat(g):
    # image gradients may be expanded (stride 0) or otherwise strided; the kernels index them flat
    return g if g.is_contiguous() or all(st == 0 for st in g.stride()) else g.contiguous()


_OFFSET_POS = 8  # index of `tile_offset` in both tile kernels' argument lists


def render_forward(proj, pthr, tile_start, entries, bg, width, height, color, depth, dnorm, alpha, t_final, last,
                   hits, device, count_hits: bool = True) -> None:
    """count_hits is accepted for the backends' common signature; these kernels always write hits."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    inputs = [to_warp(proj), to_warp(pthr), to_warp(tile_start), to_warp(entries), to_warp(bg), width, height,
              tiles_x, 0, *(to_warp_1d(t) for t in (color, depth, dnorm, alpha, t_final, last)), to_warp(hits)]
    kernel = _cpu.forward if device == "cpu" and CPU_COMPOSITE == "vector" else _forward
    launch_tiles(kernel, tiles_x * tiles_y, inputs, 2 * entries.shape[0], device)
    if device == "cuda":
        wp.synchronize_device(device)


def render_backward(proj, pthr, tile_start, entries, bg, width, height, t_final, dnorm, last, g_color, g_depth,
                    g_dnorm, g_alpha, g_entry, device) -> None:
    g_color, g_depth, g_dnorm, g_alpha = (_flat(g) for g in (g_color, g_depth, g_dnorm, g_alpha))  # held: launched
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    inputs = [to_warp(proj), to_warp(pthr), to_warp(tile_start), to_warp(entries), to_warp(bg), width, height,
              tiles_x, 0, *(to_warp_1d(t) for t in (t_final, dnorm, last, g_color, g_depth, g_dnorm, g_alpha))]
    if device == "cpu" and CPU_COMPOSITE == "vector":  # its per-pixel scratch lives in the tile's local arrays
        launch_tiles(_cpu.backward, tiles_x * tiles_y, inputs + [to_warp(g_entry)], 2 * g_entry.shape[0], device)
        return
    t_run, behind, g_dep = (torch.empty_like(t_final) for _ in range(3))  # the per-pixel scratch of the reverse pass
    inputs += [to_warp_1d(t_run), to_warp_1d(behind), to_warp_1d(g_dep), to_warp(g_entry)]
    launch_tiles(_backward, tiles_x * tiles_y, inputs, 2 * g_entry.shape[0], device)
    if device == "cuda":
        wp.synchronize_device(device)
