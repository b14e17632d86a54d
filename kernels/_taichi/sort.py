"""Taichi kernels that turn projected Gaussians into depth-ordered per-tile lists, and per-Gaussian hit counts.

Same contract as kernels/_warp/sort.py (read its docstring). On the CPU: one serial pass (the whole body sits
in a one-iteration outer loop, so Taichi runs every inner loop in order) doing the tile-count scan, a stable
3 x 11-bit LSD radix sort by the depth's bit pattern, and the counting sort into per-tile lists; 32-bit integers
only, no atomics, no recursion. On the GPU archs (CUDA, Vulkan): kernels/binning.py's parallel steps around the
`_tile_ids` scatter (one Gaussian per thread), the same lists bit for bit. `count_touched` runs one iteration per
Gaussian.
"""

import taichi as ti

from ..binning import bin_parallel
from .launch import on_cpu

RADIX_BITS = 11
RADIX = 1 << RADIX_BITS
# "serial": the CPU bins with `_bin` below; "parallel": with the GPU archs' steps (kept on the CPU for tests)
CPU_BIN = "serial"

_i1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
_i2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


@ti.func
def _radix_pass(src_k: ti.template(), src_v: ti.template(), dst_k: ti.template(), dst_v: ti.template(),
                hist: ti.template(), m, shift):
    for b in range(RADIX):
        hist[b] = 0
    for i in range(m):
        d = (src_k[i] >> shift) & (RADIX - 1)
        hist[d] = hist[d] + 1
    s = 0
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


@ti.kernel
def _bin(zbits: _i2, ntiles: _i1, rect: _i2, n: ti.i32, tiles_x: ti.i32, n_tiles: ti.i32, capacity: ti.i32,
         status: _i1, emit_start: _i1, keys: _i1, vals: _i1, keys2: _i1, vals2: _i1, hist: _i1, tile_start: _i1,
         cursor: _i1, entries: _i1, emit_pos: _i1):
    for _once in range(1):
        total = 0
        bad = 0
        m = 0
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
        if bad == 0 and total <= capacity:
            _radix_pass(keys, vals, keys2, vals2, hist, m, 0)
            _radix_pass(keys2, vals2, keys, vals, hist, m, RADIX_BITS)
            _radix_pass(keys, vals, keys2, vals2, hist, m, 2 * RADIX_BITS)  # front to back in vals2
            for t in range(n_tiles + 1):
                tile_start[t] = 0
            for i in range(m):
                g = vals2[i]
                for ty in range(rect[g, 1], rect[g, 3]):
                    for tx in range(rect[g, 0], rect[g, 2]):
                        tile_start[ty * tiles_x + tx + 1] = tile_start[ty * tiles_x + tx + 1] + 1
            for t in range(n_tiles):
                tile_start[t + 1] = tile_start[t + 1] + tile_start[t]
                cursor[t] = tile_start[t]
            for i in range(m):
                g = vals2[i]
                k = emit_start[g]
                for ty in range(rect[g, 1], rect[g, 3]):
                    for tx in range(rect[g, 0], rect[g, 2]):
                        t = ty * tiles_x + tx
                        pos = cursor[t]
                        cursor[t] = pos + 1
                        entries[pos] = g
                        emit_pos[k] = pos
                        k += 1


@ti.kernel
def _tile_ids(rect: _i2, ntiles: _i1, emit_start: _i1, n: ti.i32, tiles_x: ti.i32, tiles: _i1):
    # Gaussian g's entries, from emit_start[g] on, name the tiles of its rectangle in row-major order
    for g in range(n):
        if ntiles[g] > 0:
            k = emit_start[g]
            for ty in range(rect[g, 1], rect[g, 3]):
                for tx in range(rect[g, 0], rect[g, 2]):
                    tiles[k] = ty * tiles_x + tx
                    k += 1


def _scatter(rect, ntiles, emit_start, n: int, tiles_x: int, tiles) -> None:
    _tile_ids(rect, ntiles, emit_start, n, tiles_x, tiles)
    if tiles.is_cuda:  # torch reads `tiles` next
        ti.sync()


@ti.kernel
def _touched(n: ti.i32, ntiles: _i1, emit_start: _i1, emit_pos: _i1, hits: _i1, n_touched: _i1):
    for g in range(n):
        s = 0
        nt = ntiles[g]
        if nt > 0:
            k0 = emit_start[g]
            for k in range(k0, k0 + nt):
                s += hits[emit_pos[k]]
        n_touched[g] = s


def bin_tiles(proj_bits, ntiles, rect, n: int, tiles_x: int, n_tiles: int, status, emit_start, scratch, tile_start,
              cursor, entries, emit_pos, device: str) -> None:
    """proj_bits [>=n, 10] int32 view of the projected rows; scratch [5, >= max(n, RADIX)] int32."""
    if not on_cpu() or CPU_BIN == "parallel":
        bin_parallel(_scatter, proj_bits, ntiles, rect, n, tiles_x, n_tiles, status, emit_start, tile_start, entries,
                     emit_pos)
        return
    keys, vals, keys2, vals2, hist = (scratch[k] for k in range(5))
    _bin(proj_bits, ntiles, rect, n, tiles_x, n_tiles, entries.shape[0], status, emit_start, keys, vals, keys2,
         vals2, hist, tile_start, cursor, entries, emit_pos)
    if device == "cuda":
        ti.sync()


def count_touched(n: int, ntiles, emit_start, emit_pos, hits, n_touched, device: str) -> None:
    """n_touched[g] = sum of hits over Gaussian g's tile entries, g < n."""
    if n == 0:
        return
    _touched(n, ntiles, emit_start, emit_pos, hits, n_touched)
    if device == "cuda":
        ti.sync()
