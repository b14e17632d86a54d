"""Warp kernels that turn projected Gaussians into depth-ordered per-tile lists, and per-Gaussian hit counts.

`bin_tiles` runs steps 1-2 on one kernel thread (a serial pass, no atomics, deterministic, 32-bit integers only) and
step 3 in P parts of the depth order (one per CPU thread; 1 on CUDA and for small N), counted per part, then listed
per part after the entries of the parts before it, which gives the single pass's lists exactly:
1. an exclusive scan of the per-Gaussian tile counts (`emit_start`: where Gaussian g's tile entries are listed),
   which also compacts the visible Gaussians and counts invalid ones (ntiles = -1 from the projection);
2. a stable LSD radix sort of the visible Gaussians by camera depth — the float32 bit pattern of z > 0 read as an
   int32 orders like z — in three 11-bit passes, so equal depths keep index order (the twin's tie rule);
3. a counting sort of (tile, Gaussian) pairs by tile, visiting Gaussians front to back, so each tile's list is in
   depth order; `emit_pos[emit_start[g] + k]` records where the k-th tile (row-major over g's rectangle) of
   Gaussian g landed, so the backward can sum a Gaussian's entries without atomics.
status = [entries E, invalid Gaussians, visible Gaussians]; nothing past step 1 is written when invalid > 0 or
E > capacity (the caller grows its buffers and calls again).
"""

from __future__ import annotations

import torch
import warp as wp

from . import launch as _launch
from . import sort_cpu as _cpu
from .arrays import to_warp as _w
from .arrays import to_warp_rows
from .launch import launch, run

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

RADIX_BITS = 11
BLOCK = 256  # CPU: Gaussians per kernel thread of _touched (a Warp CPU launch pays per thread)
RADIX = 1 << RADIX_BITS
# "native": the CPU bins with kernels/_warp/sort_cpu.py (the same steps in C++, the same outputs bit for bit);
# "warp": with the kernels below (the CUDA ones; kept on the CPU as a peer and for tests)
CPU_SORT = "native"
# CPU only (a no-op on CUDA): the counting sort visits Gaussians in depth order, so their rectangles and entry
# starts are random reads; fetch those of the Gaussian 8 places ahead into cache (measured: binning 256k Gaussians of a
# real map took ~0.3 s, mostly those misses).
_PREFETCH_RECT = r"""
#if !defined(__CUDA_ARCH__)
    const int ahead = 8;
    if (i + ahead < m) {
        const int g = *(const int*)((const char*)order.data + (size_t)(i + ahead) * order.strides[0]);
        __builtin_prefetch((const char*)rect.data + (size_t)g * rect.strides[0]);
        __builtin_prefetch((const char*)emit_start.data + (size_t)g * emit_start.strides[0]);
    }
#endif
"""


@wp.func_native(_PREFETCH_RECT)
def _prefetch_rect(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                   emit_start: wp.array(dtype=wp.int32), i: int, m: int):
    ...


@wp.func
def _radix_pass(src_k: wp.array(dtype=wp.int32), src_v: wp.array(dtype=wp.int32), dst_k: wp.array(dtype=wp.int32),
                dst_v: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32), m: int, shift: int):
    for b in range(RADIX):
        hist[b] = 0
    for i in range(m):
        d = (src_k[i] >> shift) & (RADIX - 1)
        hist[d] = hist[d] + 1
    s = int(0)
    for b in range(RADIX):
        c = hist[b]
        hist[b] = s
        s += c
    for i in range(m):
        d = (src_k[i] >> shift) & (RADIX - 1)
        j = hist[d]
        hist[d] = j + 1
        dst_k[j] = src_k[i]
        dst_v[j] = src_v[i]
    return 0


@wp.kernel
def _bin(zbits: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), n: int, capacity: int,
         status: wp.array(dtype=wp.int32),
         emit_start: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.int32),
         keys2: wp.array(dtype=wp.int32), vals2: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    total = int(0)
    bad = int(0)
    m = int(0)
    for g in range(n):
        c = ntiles[g]
        emit_start[g] = total
        if c < 0:
            bad += 1
        elif c > 0:
            total += c
            keys[m] = zbits[g, 9]
            vals[m] = g
            m += 1
    status[0] = total
    status[1] = bad
    status[2] = m
    if bad > 0 or total > capacity:
        return
    _radix_pass(keys, vals, keys2, vals2, hist, m, 0)
    _radix_pass(keys2, vals2, keys, vals, hist, m, RADIX_BITS)
    _radix_pass(keys, vals, keys2, vals2, hist, m, 2 * RADIX_BITS)  # front to back in vals2
    # the per-tile lists: _tile_counts, then _tile_lists


@wp.func
def _part(m: int, p: int, parts: int) -> int:
    # first depth-order position of part p of `parts` (int64 products: no overflow)
    return int(wp.int64(m) * wp.int64(p) // wp.int64(parts))


@wp.kernel
def _tile_counts(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                 emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int, tiles_x: int,
                 n_tiles: int, parts: int, offset: int, counts: wp.array2d(dtype=wp.int32)):
    # thread p: counts[p, t] = entries of tile t from part p of the depth-ordered Gaussians
    p = wp.tid() + offset
    if status[1] > 0 or status[0] > capacity:
        return
    m = status[2]
    for t in range(n_tiles):
        counts[p, t] = 0
    end = _part(m, p + 1, parts)
    for i in range(_part(m, p, parts), end):
        _prefetch_rect(order, rect, emit_start, i, end)
        g = order[i]
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                t = ty * tiles_x + tx
                counts[p, t] = counts[p, t] + 1


@wp.kernel
def _tile_lists(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int, tiles_x: int,
                n_tiles: int, parts: int, offset: int, counts: wp.array2d(dtype=wp.int32),
                cursor: wp.array2d(dtype=wp.int32), tile_start: wp.array(dtype=wp.int32),
                entries: wp.array(dtype=wp.int32), emit_pos: wp.array(dtype=wp.int32)):
    # thread p: lists part p's Gaussians front to back after those of parts < p (so every tile's list is in
    # depth order); thread 0 also writes tile_start, the exclusive scan of the tiles' entry counts
    p = wp.tid() + offset
    if status[1] > 0 or status[0] > capacity:
        return
    m = status[2]
    s = int(0)
    for t in range(n_tiles):
        c = s
        for q in range(parts):
            if q < p:
                c += counts[q, t]
            s += counts[q, t]
        cursor[p, t] = c
        if p == 0:
            tile_start[t] = c
    if p == 0:
        tile_start[n_tiles] = s
    end = _part(m, p + 1, parts)
    for i in range(_part(m, p, parts), end):
        _prefetch_rect(order, rect, emit_start, i, end)
        g = order[i]
        k = emit_start[g]
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                t = ty * tiles_x + tx
                pos = cursor[p, t]
                cursor[p, t] = pos + 1
                entries[pos] = g
                emit_pos[k] = pos
                k += 1


@wp.kernel
def _touched(ntiles: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32),
             emit_pos: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32), offset: int, count: int, n: int,
             n_touched: wp.array(dtype=wp.int32)):
    # thread = Gaussians [count (tid + offset), + count) (CUDA: count 1; CPU: blocks, as the projection)
    g0 = (wp.tid() + offset) * count
    for g in range(g0, wp.min(g0 + count, n)):
        s = int(0)
        nt = ntiles[g]
        if nt > 0:
            k0 = emit_start[g]
            for k in range(k0, k0 + nt):
                s += hits[emit_pos[k]]
        n_touched[g] = s


def bin_tiles(proj_bits, ntiles, rect, n: int, tiles_x: int, n_tiles: int, status, emit_start, scratch, tile_start, cursor,
              entries, emit_pos, device: str) -> None:
    """proj_bits [>=n, 10] int32 view of the projected rows; scratch [5, >= max(n, RADIX)] int32; see the module doc.
    (`cursor` [n_tiles] is the Taichi kernel's; here the per-tile lists are built in parts, one per CPU thread.)"""
    keys, vals, keys2, vals2, hist = to_warp_rows(scratch)
    native = device == "cpu" and CPU_SORT == "native"
    parts = _launch._cpu_threads() if device == "cpu" and n >= _launch.MIN_SPLIT else 1
    tmp = torch.empty(2, parts, n_tiles, dtype=torch.int32, device=scratch.device)
    counts, cursors = to_warp_rows(tmp)
    sort_args = [_w(proj_bits), _w(ntiles), n, entries.shape[0], _w(status), _w(emit_start), keys, vals, keys2,
                 vals2, hist]
    if native and parts == 1:  # the three steps in one launch
        run(_cpu.bin_whole, 1, sort_args + [_w(rect), tiles_x, n_tiles, counts, cursors, _w(tile_start),
                                            _w(entries), _w(emit_pos)], device)
        return
    k_bin, k_counts, k_lists = (_cpu.bin_sort, _cpu.tile_counts, _cpu.tile_lists) if native else \
        (_bin, _tile_counts, _tile_lists)
    run(k_bin, 1, sort_args, device)
    common = [vals2, _w(rect), _w(emit_start), _w(status), entries.shape[0], tiles_x, n_tiles, parts, 0, counts]
    launch(k_counts, parts, common, 8, device, work=n)
    launch(k_lists, parts, common + [cursors, _w(tile_start), _w(entries), _w(emit_pos)], 8, device, work=n)


def count_touched(n: int, ntiles, emit_start, emit_pos, hits, n_touched, device: str) -> None:
    """n_touched[g] = sum of hits over Gaussian g's tile entries, g < n."""
    if n == 0:
        return
    count = BLOCK if device == "cpu" else 1
    launch(_touched, (n + count - 1) // count, [_w(ntiles), _w(emit_start), _w(emit_pos), _w(hits), 0, count, n,
                                                _w(n_touched)], 4, device, work=n)
