"""Solved fraction of real image pairs per pair backend: Redwood livingroom1 (211 frames, 640x480) pairs 5-60 deg
apart with overlapping views, judged against the sequence's pseudo ground truth (perf/redwood_pairs.py).

Solved = rotation error < 5 deg and translation-direction error < 15 deg (the issue's criterion). Time per pair =
encoding both images + registering them, wall clock (scales with the machine's load) and process CPU time.
Peer: the classical SIFT backend in the same run. Needs /work/shared/data/redwood_livingroom1_211 (or
SWARMSPLAT_REDWOOD211); without it the subject reports that and returns no rows.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

import numpy as np

DESCRIPTION = "real pairs: solved % (rot < 5 deg, dir < 15 deg) of Redwood pairs 5-60 deg apart per pair backend"
DATA = Path(os.environ.get("SWARMSPLAT_REDWOOD211", "/work/shared/data/redwood_livingroom1_211"))

# (row label, make_registrar name, options): the peer first
BACKENDS = (("classical", "classical", {}), ("xfeat", "xfeat", {}),
            ("xfeat top_k=2048", "xfeat", {"top_k": 2048}))


def evaluate(registrar, seq, pairs: list[dict]) -> dict:
    """Register every pair from scratch (both encodings timed) -> solved per bin, times per pair."""
    from kernels import se3
    from perf.redwood_pairs import is_solved

    cam = seq.camera
    solved, wall, cpu, corr = [], [], [], []
    images: dict[int, np.ndarray] = {}
    for p in pairs:
        for k in (p["i"], p["j"]):
            if k not in images:
                images[k] = seq[k].color
        T = se3.inverse(seq.gt_poses[p["i"]]) @ seq.gt_poses[p["j"]]
        t0, c0 = time.perf_counter(), time.process_time()
        res = registrar.register(registrar.encode(images[p["i"]]), registrar.encode(images[p["j"]]), cam, cam)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        solved.append(is_solved(res, T))
        corr.append(res.n_correspondences)
    out = {"solved": solved, "pair_ms": 1e3 * statistics.median(wall), "pair_cpu_ms": 1e3 * statistics.median(cpu),
           "median_corr": float(np.median(corr))}
    return out


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from perf.redwood_pairs import ROT_BINS, load_sequence, sample_pairs
    from registration.pair import make_registrar

    cols = ["backend", "pairs", "solved_pct"] + [f"solved_{lo:g}-{hi:g}" for lo, hi in ROT_BINS] + \
        ["pair_ms", "pair_cpu_ms", "median_corr", "time_vs_peer"]
    if not DATA.is_dir():
        return {"rows": [], "columns": cols, "notes": [f"{DATA} not found: no real pairs measured"]}
    load = os.getloadavg()[0]
    seq = load_sequence(DATA)
    per_bin = 8 if quick else 30
    pairs = sample_pairs(seq, per_bin=per_bin, seed=0)
    bins = [p["bin"] for p in pairs]
    rows, peer = [], None
    for label, name, opts in (BACKENDS[:2] if quick else BACKENDS):
        r = evaluate(make_registrar(name, **opts), seq, pairs)
        s = np.array(r["solved"])
        row = {"backend": label, "pairs": len(pairs), "solved_pct": 100.0 * s.mean(),
               "pair_ms": r["pair_ms"], "pair_cpu_ms": r["pair_cpu_ms"], "median_corr": r["median_corr"]}
        for lo, hi in ROT_BINS:
            m = np.array([b == f"{lo:g}-{hi:g}" for b in bins])
            row[f"solved_{lo:g}-{hi:g}"] = 100.0 * s[m].mean() if m.any() else float("nan")
        peer = peer or row
        row["time_vs_peer"] = row["pair_ms"] / peer["pair_ms"]
        rows.append(row)
    notes = [f"{len(pairs)} pairs of {DATA.name} ({per_bin} per bin {', '.join(f'{lo:g}-{hi:g}' for lo, hi in ROT_BINS)}"
             f" deg, co-visibility >= 0.3 by depth, seed 0); poses: the sequence's Open3D estimate (pseudo ground "
             f"truth)", f"1-minute load average at start {load:.1f} on {os.cpu_count()} CPUs (wall times scale with "
             f"it; CPU ms do not)"]
    return {"rows": rows, "columns": cols, "notes": notes}
