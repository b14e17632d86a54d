"""Timestamp association: pair two lists of stamps by nearest time within a tolerance.

`match_nearest` follows evo's `matching_time_indices` rule exactly (each stamp of the first list takes its
nearest stamp of the second within `max_diff`; a stamp of the second list may serve several), so ATE/RPE
computed on its pairs equal evo's. `associate_unique` is the one-to-one greedy pairing of TUM's `associate.py`,
used to pair RGB with depth frames recorded by two clocks.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.errors import InputError


def match_nearest(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float = 0.01,
                  offset_2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i1 [K], i2 [K]) pairing each stamp of `stamps_1` with its nearest in `stamps_2` (seconds).

    A pair is kept when |stamps_1[i1] - (stamps_2[i2] + offset_2)| <= max_diff. Ties prefer the earlier stamp
    of `stamps_2`. Unsorted `stamps_2` falls back to a brute-force search with the same result rule.
    """
    s1 = np.asarray(stamps_1, dtype=np.float64).reshape(-1)
    s2 = np.asarray(stamps_2, dtype=np.float64).reshape(-1) + offset_2
    if max_diff < 0:
        raise InputError(f"association tolerance max_diff must be >= 0, got {max_diff}")
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if np.all(np.diff(s2) >= 0):
        inside = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
        ub = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
        diff_ub = s2[ub] - s1
        diff_lb = np.where(ub > 0, s1 - s2[np.maximum(ub - 1, 0)], np.inf)
        take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
        take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
        keep = inside & (take_ub | take_lb)
        best = np.where(take_ub, ub, ub - 1)
        i1 = np.nonzero(keep)[0]
        return i1.astype(np.int64), best[keep].astype(np.int64)
    i1, i2 = [], []
    for k, t in enumerate(s1):
        d = np.abs(s2 - t)
        j = int(np.argmin(d))
        if d[j] <= max_diff:
            i1.append(k)
            i2.append(j)
    return np.asarray(i1, dtype=np.int64), np.asarray(i2, dtype=np.int64)


def associate_unique(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float = 0.02,
                     offset_2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs (i1 [K], i2 [K]), sorted by i1: greedily the closest remaining pair first, as TUM's tool.

    Each stamp is used at most once; pairs further apart than `max_diff` seconds are dropped.
    """
    s1 = np.asarray(stamps_1, dtype=np.float64).reshape(-1)
    s2 = np.asarray(stamps_2, dtype=np.float64).reshape(-1) + offset_2
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    # Every pair within the tolerance is a candidate (a window per stamp, found by binary search), which is
    # what TUM's script considers, without its O(N*M) table.
    order2 = np.argsort(s2, kind="stable")
    s2s = s2[order2]
    lo = np.searchsorted(s2s, s1 - max_diff, side="left")
    hi = np.searchsorted(s2s, s1 + max_diff, side="right")
    cand = [(k, int(order2[j])) for k in range(len(s1)) for j in range(lo[k], hi[k])]
    pairs = sorted(cand, key=lambda p: (abs(s1[p[0]] - s2[p[1]]), p[0], p[1]))
    used1, used2, out = set(), set(), []
    for a, b in pairs:
        if a not in used1 and b not in used2:
            used1.add(a)
            used2.add(b)
            out.append((a, b))
    out.sort()
    if not out:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    arr = np.asarray(out, dtype=np.int64)
    return arr[:, 0], arr[:, 1]
