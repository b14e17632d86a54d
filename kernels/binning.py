"""The GPU binning of the rasteriser: per-tile, depth-ordered lists built with parallel steps, as GPU 3DGS
rasterisers do (count, exclusive prefix sum, key scatter, one sort of (tile, depth) keys).

Both backends run it on their GPU devices (Warp on CUDA, Taichi on CUDA and Vulkan); only the key scatter is a
kernel of the backend (`tile_ids`: one thread per Gaussian writes the tile of each of its entries), the rest are
torch operations on the tensors' device (on Vulkan the CPU's). No step runs longer than one Gaussian's tile
rectangle per thread, which is what a GPU wants, and what Mesa's software Vulkan driver needs (it stops any one
invocation's loops after 65535 iterations in total).

The lists equal those of the serial CPU binning (kernels/_warp/sort.py's module docstring has the contract) bit
for bit: a Gaussian's entries are emitted at `emit_start[g]` in the row-major order of its tile rectangle,
Gaussians in index order, and a *stable* sort by key = tile * 2^31 + (float32 bit pattern of z > 0, which orders
like z) keeps index order among equal depths in a tile — the twin's tie rule. `emit_pos[k]` is where emission k
landed.
"""

from __future__ import annotations

import torch

_I32, _I64 = torch.int32, torch.int64


def bin_parallel(tile_ids, zbits, ntiles, rect, n: int, tiles_x: int, n_tiles: int, status, emit_start, tile_start,
                 entries, emit_pos) -> None:
    """Fill status [3] = (entries E, invalid Gaussians, visible Gaussians), emit_start [>= n], and, when no
    Gaussian is invalid and E <= len(entries): tile_start [n_tiles + 1], entries [E], emit_pos [E].

    tile_ids(rect, ntiles, emit_start, n, tiles_x, out [E] int32): the backend's scatter kernel; zbits [>= n, 10]
    int32 view of the projected rows (column 9: depth); ntiles [>= n] int32 (-1: invalid input); rect [>= n, 4]
    int32 tile rectangles (x0, y0, x1, y1), end exclusive.
    """
    dev = ntiles.device
    nt = ntiles[:n]
    counts = nt.clamp(min=0)
    ends = torch.cumsum(counts, 0, dtype=_I64) if n else torch.zeros(1, dtype=_I64, device=dev)
    total = int(ends[-1])
    bad = int((nt < 0).sum())
    emit_start[:n] = (ends - counts).to(_I32)
    status.copy_(torch.tensor([total, bad, int((nt > 0).sum())], dtype=_I32))
    if bad or total > entries.shape[0]:
        return
    if total == 0:
        tile_start.zero_()
        return
    tiles = torch.empty(total, dtype=_I32, device=dev)
    tile_ids(rect, ntiles, emit_start, n, tiles_x, tiles)
    gauss = torch.repeat_interleave(torch.arange(n, dtype=_I32, device=dev), counts)
    key = (tiles.to(_I64) << 31) | zbits[:n, 9].to(_I64)[gauss.long()]
    order = torch.sort(key, stable=True).indices
    entries[:total] = gauss[order]
    emit_pos[order] = torch.arange(total, dtype=_I32, device=dev)
    tile_start[0] = 0
    tile_start[1:] = torch.cumsum(torch.bincount(tiles, minlength=n_tiles), 0)
