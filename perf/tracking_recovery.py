"""Standalone perf module: does the recovery of a failed coarse stage (tracking.recovery: a learned start
against the previous frame, then re-localisation against the submap's keyframes) hold tracking together under
large motion, and what does it cost?

Fast motion is emulated by taking every k-th frame of a real sequence (Redwood living room 1: k = 8 is ~14 cm /
5 deg mean between frames). Per stride, one agent runs the strided sequence with the recovery off and on, in the
same process, with the default configuration otherwise (loop closure on, as `swarmsplat run`). Per run: ATE
(SE(3)-aligned; with and without loop closure), the tracking time per frame, and the recovery counters
(metrics.json `tracking_recoveries`).

    python -m perf.tracking_recovery        # strides 4-16 of Redwood 211 -> perf/results/tracking-recovery-cpu.*
    python -m perf.tracking_recovery --hard # the same frames with depth noise, holes and blur (-hard-cpu.*)
    python -m perf.tracking_recovery --strides 8 --frames 20 --json out.json --md out.md
    python -m perf.tracking_recovery --from-json perf/results/tracking-recovery-cpu.json   # rewrite its .md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DESCRIPTION = "tracking recovery off vs on over strided real frames: ATE, tracking time, recoveries"

ROOT = Path(__file__).resolve().parents[1]
REDWOOD = ROOT / ".." / "shared" / "data" / "redwood_livingroom1_211"
RESULTS = ROOT / "perf" / "results"


def strided(seq, k: int):
    """Every k-th frame of an ImageSequence (slam.io.datasets), timestamps and ground truth kept with them."""
    from swarmsplat.slam.io.datasets import ImageSequence

    gt = seq.gt_poses
    odom = seq.odometry
    return ImageSequence(
        name=f"{seq.name}-every{k}", root=seq.root, camera=seq.camera, timestamps=seq.timestamps[::k],
        color_paths=seq.color_paths[::k], depth_paths=None if seq.depth_paths is None else seq.depth_paths[::k],
        depth_scale=seq.depth_scale, gt_poses=None if gt is None else gt[::k],
        odometry=None if odom is None else odom[::k], color_transform=seq._color_transform)


class Harder:
    """A sequence with its frames made harder, seeded by frame index: depth noise growing with range (sigma 1.5 mm
    + 0.5 % of depth), 8 holes of 40-120 px in the depth, and a 9 px horizontal motion blur on the colour."""

    def __init__(self, seq):
        self.seq = seq

    def __getattr__(self, name):
        return getattr(self.seq, name)

    def __len__(self) -> int:
        return len(self.seq)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __getitem__(self, i: int):
        import dataclasses

        import cv2

        f = self.seq[i]
        rng = np.random.default_rng(1000 + int(f.index))
        d = f.depth.copy()
        ok = d > 0
        d[ok] += rng.normal(0.0, 1.0, int(ok.sum())) * (0.0015 + 0.005 * d[ok])
        h, w = d.shape
        for _ in range(8):
            hh, ww = rng.integers(40, 121, 2)
            y, x = rng.integers(0, h - hh), rng.integers(0, w - ww)
            d[y:y + hh, x:x + ww] = 0.0
        kernel = np.full((1, 9), 1.0 / 9.0, np.float32)
        color = cv2.filter2D(f.color, -1, kernel)
        return dataclasses.replace(f, color=color, depth=d.astype(f.depth.dtype))


def step_stats(seq) -> dict:
    """Mean / max ground-truth motion between consecutive frames (cm, deg)."""
    from swarmsplat.kernels import se3

    G = seq.gt_poses
    if G is None or len(G) < 2:
        return {}
    D = [se3.inverse(a) @ b for a, b in zip(G[:-1], G[1:])]
    t = np.array([np.linalg.norm(d[:3, 3]) for d in D]) * 100
    r = np.array([np.degrees(se3.rotation_angle(d[:3, :3])) for d in D])
    return {"step_cm_mean": float(t.mean()), "step_cm_max": float(t.max()), "step_deg_mean": float(r.mean()),
            "step_deg_max": float(r.max())}


def measure(seq, recovery: bool, frames: int | None) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import run_sequence

    cfg = SlamConfig().override({"tracking": {"recovery": recovery}})
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        m = run_sequence(seq, out, cfg, frames=frames, progress=False)
        wall = time.perf_counter() - t0
    n = max(1, m["frames_tracked"])
    return {"recovery": recovery, "frames": m["frames_tracked"], "ate_cm": 100 * m["ate_rmse"],
            "ate_no_lc_cm": 100 * m.get("ate_rmse_no_lc", float("nan")),
            "tracking_ms_per_frame": 1e3 * m["time_s"]["tracking"] / n, "wall_s": wall,
            **{f"recoveries_{k}": v for k, v in m["tracking_recoveries"].items()}}


def run(data: Path = REDWOOD, strides=(4, 6, 8, 12, 16), frames: int | None = None, hard: bool = False) -> dict:
    from swarmsplat.slam.io.datasets import load_sequence

    base = load_sequence(data)
    rows = []
    for k in strides:
        seq = strided(base, k)
        stats = step_stats(seq)
        seq = Harder(seq) if hard else seq
        for recovery in (False, True):
            r = measure(seq, recovery, frames)
            rows.append({"data": data.name, "frames_made_harder": hard, "stride": k, **stats, **r})
            print(rows[-1], file=sys.stderr, flush=True)
    return {"subject": "tracking-recovery", "data": str(data), "hard": hard, "rows": rows}


def markdown(res: dict) -> str:
    from .common import markdown_table

    cols = ["stride", "step_cm_mean", "step_cm_max", "step_deg_mean", "recovery", "frames", "ate_cm",
            "ate_no_lc_cm", "tracking_ms_per_frame", "recoveries_coarse_failed", "recoveries_attempted",
            "recoveries_retried", "recoveries_relocalised"]
    hard = res.get("hard")
    return (f"# Tracking recovery on strided real frames ({Path(res['data']).name}"
            f"{', made harder' if hard else ''})\n\n"
            "Every k-th frame, the default configuration with tracking.recovery off / on (same process)"
            f"{'; depth noise, depth holes and motion blur on every frame (Harder)' if hard else ''}."
            f" Command: `python -m perf.tracking_recovery{' --hard' if hard else ''}`.\n\n"
            + markdown_table(res["rows"], cols))


def main(argv=None) -> int:
    from .common import write_results

    p = argparse.ArgumentParser(description=DESCRIPTION)
    p.add_argument("--data", type=Path, default=REDWOOD)
    p.add_argument("--strides", default="4,6,8,12,16", help="comma-separated frame strides")
    p.add_argument("--frames", type=int, default=None, help="at most this many strided frames per run")
    p.add_argument("--hard", action="store_true", help="depth noise, depth holes and motion blur (class Harder)")
    p.add_argument("--json", default=None, help="default perf/results/tracking-recovery[-hard]-cpu.json")
    p.add_argument("--md", default=None, help="default perf/results/tracking-recovery[-hard]-cpu.md")
    p.add_argument("--from-json", type=Path, help="rewrite the Markdown of this result file and exit")
    a = p.parse_args(argv)
    if a.from_json:
        import json

        res = json.loads(a.from_json.read_text())
        write_results(None, a.md or str(a.from_json.with_suffix(".md")), res, markdown(res))
        return 0
    name = "tracking-recovery-hard-cpu" if a.hard else "tracking-recovery-cpu"
    a.json = a.json or str(RESULTS / f"{name}.json")
    a.md = a.md or str(RESULTS / f"{name}.md")
    res = run(a.data, [int(s) for s in a.strides.split(",")], a.frames, a.hard)
    md = markdown(res)
    print(md)
    write_results(a.json, a.md, res, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
