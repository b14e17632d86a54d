"""Warp kernels that turn projected Gaussians into depth-ordered per-tile lists, and per-Gaussian hit counts.

The lists (the contract every binning meets, bit for bit):
1. an exclusive scan of the per-Gaussian tile counts (`emit_start`: where Gaussian g's tile entries are listed),
   which also counts the visible Gaussians and the invalid ones (ntiles = -1 from the projection);
2. the visible Gaussians stably ordered by camera depth — the float32 bit pattern of z > 0 read as an int32
   orders like z — so equal depths keep index order (the twin's tie rule);
3. per tile, its Gaussians in that order (`tile_start`, `entries`); `emit_pos[emit_start[g] + k]` records where
   the k-th tile (row-major over g's rectangle) of Gaussian g landed, so the backward can sum a Gaussian's entries
   without atomics.
status = [entries E, invalid Gaussians, visible Gaussians]; nothing past step 1 is written when invalid > 0 or
E > capacity (the caller grows its buffers and calls again).

On the CPU (CPU_SORT = "native") kernels/_warp/sort_cpu.py does this serially in C++: a scan, a 3 x 11-bit LSD
radix sort, and a counting sort by tile in P parts of the depth order (one per CPU thread, 1 for small N), counted
per part, then listed per part after the entries of the parts before it. On CUDA (and on the CPU with
CPU_SORT = "warp") the parallel steps of kernels/binning.py run around `_tile_ids`, one Gaussian per thread.
"""

from __future__ import annotations

import torch
import warp as wp

from ..binning import bin_parallel
from . import launch as _launch
from . import sort_cpu as _cpu
from .arrays import to_warp as _w
from .arrays import to_warp_rows
from .launch import launch, run

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

BLOCK = 256  # CPU: Gaussians per kernel thread of _touched (a Warp CPU launch pays per thread)
# "native": the CPU bins with kernels/_warp/sort_cpu.py; "warp": with the parallel (CUDA) steps, kept on the CPU
# as a peer and for tests (the same outputs bit for bit: one stable order has one result)
CPU_SORT = "native"


@wp.kernel
def _tile_ids(rect: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32),
              emit_start: wp.array(dtype=wp.int32), tiles_x: int, tiles: wp.array(dtype=wp.int32)):
    # thread g: Gaussian g's entries, from emit_start[g] on, name the tiles of its rectangle in row-major order
    g = wp.tid()
    if ntiles[g] <= 0:
        return
    k = emit_start[g]
    for ty in range(rect[g, 1], rect[g, 3]):
        for tx in range(rect[g, 0], rect[g, 2]):
            tiles[k] = ty * tiles_x + tx
            k += 1


def _scatter(device: str):
    def tile_ids(rect, ntiles, emit_start, n: int, tiles_x: int, tiles) -> None:
        run(_tile_ids, n, [_w(rect), _w(ntiles), _w(emit_start), tiles_x, _w(tiles)], device)
    return tile_ids


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
    if device != "cpu" or CPU_SORT != "native":
        bin_parallel(_scatter(device), proj_bits, ntiles, rect, n, tiles_x, n_tiles, status, emit_start, tile_start,
                     entries, emit_pos)
        return
    keys, vals, keys2, vals2, hist = to_warp_rows(scratch)
    parts = _launch._cpu_threads() if device == "cpu" and n >= _launch.MIN_SPLIT else 1
    tmp = torch.empty(2, parts, n_tiles, dtype=torch.int32, device=scratch.device)
    counts, cursors = to_warp_rows(tmp)
    sort_args = [_w(proj_bits), _w(ntiles), n, entries.shape[0], _w(status), _w(emit_start), keys, vals, keys2,
                 vals2, hist]
    if parts == 1:  # the three steps in one launch
        run(_cpu.bin_whole, 1, sort_args + [_w(rect), tiles_x, n_tiles, counts, cursors, _w(tile_start),
                                            _w(entries), _w(emit_pos)], device)
        return
    run(_cpu.bin_sort, 1, sort_args, device)
    common = [vals2, _w(rect), _w(emit_start), _w(status), entries.shape[0], tiles_x, n_tiles, parts, 0, counts]
    launch(_cpu.tile_counts, parts, common, 8, device, work=n)
    launch(_cpu.tile_lists, parts, common + [cursors, _w(tile_start), _w(entries), _w(emit_pos)], 8, device, work=n)


def count_touched(n: int, ntiles, emit_start, emit_pos, hits, n_touched, device: str) -> None:
    """n_touched[g] = sum of hits over Gaussian g's tile entries, g < n."""
    if n == 0:
        return
    count = BLOCK if device == "cpu" else 1
    launch(_touched, (n + count - 1) // count, [_w(ntiles), _w(emit_start), _w(emit_pos), _w(hits), 0, count, n,
                                                _w(n_touched)], 4, device, work=n)
