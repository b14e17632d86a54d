"""CPU binning kernels of the Warp rasteriser in native code: the same three steps as kernels/_warp/sort.py (its
module docstring has the rules), with the same arguments and the same outputs bit for bit (a stable sort has one
result), written as C++ over plain pointers.

Warp's CPU code generator indexes every array through its runtime strides and keeps loop counters and partial
sums in memory-backed variables, which made the serial scan and radix sort ~1.3 ms and each part's tile counting
and listing ~0.7-0.9 ms at 320x240 with 60k Gaussians (a tenth of a mapping iteration). Here the radix sort takes
its three 11-bit histograms in one read of the keys and skips a pass whose digit is the same for every key; the
per-part loops read the Gaussians' rectangles through prefetches as there. A rectangle of at most 2 x 2 tiles (nearly
every Gaussian at 320x240) is counted and listed as four fixed slots, absent ones adding 0 or writing to a sink,
instead of loops whose trip counts the branch predictor cannot guess: at 320x240 / 60k counting 0.78 -> 0.44 ms
and listing 0.97 -> 0.77 ms (two parts). CPU only: on CUDA the Warp kernels run.
"""

from __future__ import annotations

import warp as wp

CPU_ONLY = True  # perf/gpu_codegen.py does not build this module for CUDA

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

RADIX_BITS = 11

_COMMON = r"""
    auto ptr_i = [](const wp::array_t<int>& a) -> int* { return (int*)a.data; };
    auto step = [](const wp::array_t<int>& a) -> size_t { return a.strides[0] / sizeof(int); };
"""

_BIN = _COMMON + r"""
    const int RB = 11, R = 1 << 11;
    const int* nt = ptr_i(ntiles);
    const size_t snt = step(ntiles);
    int* es = ptr_i(emit_start);
    const size_t ses = step(emit_start);
    int *k0 = ptr_i(keys), *v0 = ptr_i(vals), *k1 = ptr_i(keys2), *v1 = ptr_i(vals2);  // hist: unused here
    const size_t sk0 = step(keys), sv0 = step(vals), sk1 = step(keys2), sv1 = step(vals2);
    const char* zb = (const char*)zbits.data;
    const size_t zs0 = zbits.strides[0], zoff = 9 * zbits.strides[1];
    int total = 0, bad = 0, m = 0;
    for (int g = 0; g < n; ++g) {
        const int c = nt[g * snt];
        es[g * ses] = total;
        if (c < 0) {
            bad += 1;
        } else if (c > 0) {
            total += c;
            k0[m * sk0] = *(const int*)(zb + (size_t)g * zs0 + zoff);
            v0[m * sv0] = g;
            m += 1;
        }
    }
    int* st = ptr_i(status);
    const size_t sst = step(status);
    st[0] = total;
    st[1] = bad;
    st[2] = m;
    if (bad > 0 || total > capacity)
        return;
    // the three digits' histograms in one read of the keys
    int hist3[3][2048];
    for (int d = 0; d < 3; ++d)
        for (int b = 0; b < R; ++b) hist3[d][b] = 0;
    for (int i = 0; i < m; ++i) {
        const unsigned key = (unsigned)k0[i * sk0];
        hist3[0][key & (R - 1)] += 1;
        hist3[1][(key >> RB) & (R - 1)] += 1;
        hist3[2][(key >> (2 * RB)) & (R - 1)] += 1;
    }
    // LSD passes, ping-ponging between (keys, vals) and (keys2, vals2); a pass whose digit is one value for every
    // key leaves the order as it is and is skipped. The sorted order must end in vals2 (the caller reads it there).
    int *sk = k0, *sv = v0, *dk = k1, *dv = v1;
    size_t ssk = sk0, ssv = sv0, sdk = sk1, sdv = sv1;
    bool in_second = false;  // the current order lives in (keys2, vals2)
    for (int d = 0; d < 3; ++d) {
        int* hd = hist3[d];
        bool one = false;
        for (int b = 0; b < R; ++b) one = one || hd[b] == m;
        if (one)
            continue;
        int s = 0;
        for (int b = 0; b < R; ++b) { const int c = hd[b]; hd[b] = s; s += c; }
        const int shift = d * RB;
        for (int i = 0; i < m; ++i) {
            const int key = sk[i * ssk];
            const int b = ((unsigned)key >> shift) & (R - 1);
            const int j = hd[b];
            hd[b] = j + 1;
            dk[j * sdk] = key;
            dv[j * sdv] = sv[i * ssv];
        }
        int* tk = sk; sk = dk; dk = tk;
        int* tv = sv; sv = dv; dv = tv;
        size_t t1 = ssk; ssk = sdk; sdk = t1;
        size_t t2 = ssv; ssv = sdv; sdv = t2;
        in_second = !in_second;
    }
    if (!in_second)  // the order is in (keys, vals): copy the values to vals2
        for (int i = 0; i < m; ++i) v1[i * sv1] = v0[i * sv0];
"""

_PART = r"""
    auto part_of = [](int m, int p, int parts) -> int { return (int)((long long)m * p / parts); };
    const int* st = (const int*)status.data;
    const size_t sst = status.strides[0] / sizeof(int);
    if (st[sst] > 0 || st[0] > capacity)
        return;
    const int m = st[2 * sst];
    const int* ord = (const int*)order.data;
    const size_t so = order.strides[0] / sizeof(int);
    const char* rb = (const char*)rect.data;
    const size_t rs0 = rect.strides[0], rs1 = rect.strides[1];
    const int* es = (const int*)emit_start.data;
    const size_t ses = emit_start.strides[0] / sizeof(int);
    const int begin = part_of(m, p, parts), end = part_of(m, p + 1, parts);
    auto R4 = [&](int g, int k) -> int { return *(const int*)(rb + (size_t)g * rs0 + (size_t)k * rs1); };
    auto prefetch = [&](int i) {
        if (i < end) {
            const int g = ord[i * so];
            __builtin_prefetch(rb + (size_t)g * rs0);
            __builtin_prefetch(es + (size_t)g * ses);
        }
    };
"""

_COUNTS = _PART + r"""
    int* cnt = (int*)((char*)counts.data + (size_t)p * counts.strides[0]);
    const size_t sc = counts.strides[1] / sizeof(int);
    for (int t = 0; t < n_tiles; ++t) cnt[t * sc] = 0;
    for (int i = begin; i < end; ++i) {
        prefetch(i + 8);
        const int g = ord[i * so];
        const int x0 = R4(g, 0), y0 = R4(g, 1), x1 = R4(g, 2), y1 = R4(g, 3);
        const int w = x1 - x0, h = y1 - y0;
        if (w <= 2 && h <= 2) {  // most Gaussians: up to 2 x 2 tiles, without data-dependent branches
            const int t0 = y0 * tiles_x + x0;
            const int wx = w > 1, hy = h > 1;
            cnt[t0 * sc] += 1;
            cnt[(t0 + wx) * sc] += wx;
            cnt[(t0 + hy * tiles_x) * sc] += hy;
            cnt[(t0 + hy * tiles_x + wx) * sc] += wx & hy;
        } else {
            for (int ty = y0; ty < y1; ++ty)
                for (int tx = x0; tx < x1; ++tx) cnt[(ty * tiles_x + tx) * sc] += 1;
        }
    }
"""

_LISTS = _PART + r"""
    // this part's cursors: after the entries of parts < p in each tile; part 0 also writes tile_start
    int* cur = (int*)((char*)cursor.data + (size_t)p * cursor.strides[0]);
    const size_t scu = cursor.strides[1] / sizeof(int);
    const char* cb = (const char*)counts.data;
    const size_t cs0 = counts.strides[0], cs1 = counts.strides[1];
    int* ts = (int*)tile_start.data;
    const size_t sts = tile_start.strides[0] / sizeof(int);
    int s = 0;
    for (int t = 0; t < n_tiles; ++t) {
        int c = s;
        for (int q = 0; q < parts; ++q) {
            const int k = *(const int*)(cb + (size_t)q * cs0 + (size_t)t * cs1);
            c += q < p ? k : 0;
            s += k;
        }
        cur[t * scu] = c;
        if (p == 0)
            ts[t * sts] = c;
    }
    if (p == 0)
        ts[n_tiles * sts] = s;
    int* ent = (int*)entries.data;
    const size_t se = entries.strides[0] / sizeof(int);
    int* ep = (int*)emit_pos.data;
    const size_t sep = emit_pos.strides[0] / sizeof(int);
    int sink = 0;  // where the absent slots of a small rectangle write
    for (int i = begin; i < end; ++i) {
        prefetch(i + 8);
        const int g = ord[i * so];
        int k = es[g * ses];
        const int x0 = R4(g, 0), y0 = R4(g, 1), x1 = R4(g, 2), y1 = R4(g, 3);
        const int w = x1 - x0, h = y1 - y0;
        if (w <= 2 && h <= 2) {  // as in the counts: four slots in the loop's order, absent ones write to a sink
            const int wx = w > 1, hy = h > 1;
            const int t0 = y0 * tiles_x + x0;
            const int ts[4] = {t0, t0 + wx, t0 + hy * tiles_x, t0 + hy * tiles_x + wx};
            const int on[4] = {1, wx, hy, wx & hy};
            for (int j = 0; j < 4; ++j) {
                int* c = cur + ts[j] * scu;
                const int pos = *c;
                *c = pos + on[j];
                const size_t use = (size_t)0 - (size_t)on[j];  // all ones or zero: no branch
                *(int*)(((size_t)(ent + pos * se) & use) | ((size_t)&sink & ~use)) = g;
                *(int*)(((size_t)(ep + k * sep) & use) | ((size_t)&sink & ~use)) = pos;
                k += on[j];
            }
        } else {
            for (int ty = y0; ty < y1; ++ty)
                for (int tx = x0; tx < x1; ++tx) {
                    int* c = cur + (ty * tiles_x + tx) * scu;
                    const int pos = *c;
                    *c = pos + 1;
                    ent[pos * se] = g;
                    ep[k * sep] = pos;
                    k += 1;
                }
        }
    }
"""


@wp.func_native(_BIN)
def _bin_native(zbits: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), n: int, capacity: int,
                status: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32),
                keys: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.int32), keys2: wp.array(dtype=wp.int32),
                vals2: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    ...


@wp.func_native(_COUNTS)
def _counts_native(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                   emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int,
                   tiles_x: int, n_tiles: int, parts: int, p: int, counts: wp.array2d(dtype=wp.int32)):
    ...


@wp.func_native(_LISTS)
def _lists_native(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                  emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int,
                  tiles_x: int, n_tiles: int, parts: int, p: int, counts: wp.array2d(dtype=wp.int32),
                  cursor: wp.array2d(dtype=wp.int32), tile_start: wp.array(dtype=wp.int32),
                  entries: wp.array(dtype=wp.int32), emit_pos: wp.array(dtype=wp.int32)):
    ...


# The same argument lists as kernels/_warp/sort.py's _bin, _tile_counts and _tile_lists (its launches take either).
@wp.kernel
def bin_sort(zbits: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), n: int, capacity: int,
             status: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int32),
             vals: wp.array(dtype=wp.int32), keys2: wp.array(dtype=wp.int32), vals2: wp.array(dtype=wp.int32),
             hist: wp.array(dtype=wp.int32)):
    _bin_native(zbits, ntiles, n, capacity, status, emit_start, keys, vals, keys2, vals2, hist)


@wp.kernel
def tile_counts(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
                emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int, tiles_x: int,
                n_tiles: int, parts: int, offset: int, counts: wp.array2d(dtype=wp.int32)):
    _counts_native(order, rect, emit_start, status, capacity, tiles_x, n_tiles, parts, wp.tid() + offset, counts)


@wp.kernel
def tile_lists(order: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32),
               emit_start: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32), capacity: int, tiles_x: int,
               n_tiles: int, parts: int, offset: int, counts: wp.array2d(dtype=wp.int32),
               cursor: wp.array2d(dtype=wp.int32), tile_start: wp.array(dtype=wp.int32),
               entries: wp.array(dtype=wp.int32), emit_pos: wp.array(dtype=wp.int32)):
    _lists_native(order, rect, emit_start, status, capacity, tiles_x, n_tiles, parts, wp.tid() + offset, counts,
                  cursor, tile_start, entries, emit_pos)


@wp.kernel
def bin_whole(zbits: wp.array2d(dtype=wp.int32), ntiles: wp.array(dtype=wp.int32), n: int, capacity: int,
              status: wp.array(dtype=wp.int32), emit_start: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int32),
              vals: wp.array(dtype=wp.int32), keys2: wp.array(dtype=wp.int32), vals2: wp.array(dtype=wp.int32),
              hist: wp.array(dtype=wp.int32), rect: wp.array2d(dtype=wp.int32), tiles_x: int, n_tiles: int,
              counts: wp.array2d(dtype=wp.int32), cursor: wp.array2d(dtype=wp.int32),
              tile_start: wp.array(dtype=wp.int32), entries: wp.array(dtype=wp.int32),
              emit_pos: wp.array(dtype=wp.int32)):
    # the three steps in one launch and one part (a small frame: each launch costs ~20 us of Python)
    _bin_native(zbits, ntiles, n, capacity, status, emit_start, keys, vals, keys2, vals2, hist)
    _counts_native(vals2, rect, emit_start, status, capacity, tiles_x, n_tiles, 1, 0, counts)
    _lists_native(vals2, rect, emit_start, status, capacity, tiles_x, n_tiles, 1, 0, counts, cursor, tile_start,
                  entries, emit_pos)
