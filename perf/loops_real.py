"""Loop closure on real and generated RGB-D sequences: ATE with and without loop closure in the same run (the
tracking-only trajectory is kept beside the optimised one), loops by candidate source, optimisations not applied,
and — where the reference is a pseudo ground truth — how well each trajectory explains the revisit geometry.

`python -m perf loops-real [--quick] --json OUT --md OUT`. Mapping is off (tracking and loop closure do not read
the map with frame-to-model refinement off), so this measures the pose pipeline alone.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

DESCRIPTION = "loop closure: ATE with vs without loop closure (same run), loops by source, reference check"
REDWOOD = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "redwood_livingroom1_211"
# Revisit pairs of the Redwood living room: (late frame, early frame) seen from nearly the same place.
REVISITS = [(175, 10), (180, 15), (185, 5), (190, 10), (195, 15), (200, 15), (205, 20)]


def _run_agent(seq, overrides: dict, n: int | None = None):
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.config import SlamConfig

    cfg = SlamConfig().override({"mapping": {"iterations": 0, "first_iterations": 0},
                                 "tracking": {"refine": False, "refine_on_coarse_failure": False}, **overrides})
    agent = Agent(seq.camera, cfg, name=seq.name)
    t0 = time.perf_counter()
    for i in range(n or len(seq)):
        f = seq[i]
        agent.step(f.index, f.timestamp, f.color, f.depth)
    return agent, time.perf_counter() - t0


def _row(name: str, seq, agent, seconds: float) -> dict:
    from swarmsplat.slam.metrics import ate

    stamps, T = agent.trajectory(per_keyframe=True)
    _, T0 = agent.trajectory_no_lc()
    gt = seq.gt_poses
    ok = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
    e1 = ate(seq.timestamps[ok], gt[ok], stamps, T, align="se3", max_diff=1e-3).rmse
    e0 = ate(seq.timestamps[ok], gt[ok], stamps, T0, align="se3", max_diff=1e-3).rmse
    log = agent.loops.log
    src = {s: (sum(c.source == s for c in log), sum(c.source == s and c.accepted for c in log))
           for s in ("descriptor", "pose")}
    return {"sequence": name, "frames": len(stamps), "ate_cm": 100 * e1, "ate_no_lc_cm": 100 * e0,
            "candidates": len(log), "accepted": sum(c.accepted for c in log),
            "descriptor_acc": f"{src['descriptor'][1]}/{src['descriptor'][0]}",
            "pose_acc": f"{src['pose'][1]}/{src['pose'][0]}",
            "rejected_after_opt": sum(e.rejected for e in agent.loops.loops),
            "not_applied": agent.loops.not_applied, "seconds": seconds}


def _reference_check(seq, agent) -> list[dict]:
    """Point-to-plane fit (Open3D fitness / inlier RMSE at 5 cm) of each revisit pair under the pseudo ground
    truth and under our trajectory: the pose that explains the depth better has the lower RMSE."""
    from swarmsplat.registration.icp import evaluate_rgbd
    from swarmsplat.slam.dense.frames import make_rgbd

    _, T = agent.trajectory(per_keyframe=True)
    gt = seq.gt_poses
    rows = []
    for q, m in REVISITS:
        if max(q, m) >= len(T):
            continue
        f = [make_rgbd(seq[i].color, seq[i].depth, seq.camera, min_depth=0.1, max_depth=10.0).resized(320)
             for i in (q, m)]
        out = {"pair": f"{q}->{m}"}
        for label, P in (("pseudo_gt", gt), ("ours", T)):
            e = evaluate_rgbd(f[0].depth, f[1].depth, f[0].camera, np.linalg.inv(P[m]) @ P[q], max_distance=0.05)
            out[f"{label}_fitness"], out[f"{label}_rmse_mm"] = e.fitness, 1000 * e.inlier_rmse
        rows.append(out)
    return rows


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import torch

    from swarmsplat import kernels
    from swarmsplat.slam.io.datasets import load_sequence

    kernels.use(backends[0], device)
    torch.set_num_threads(1)
    rows, notes, ref = [], [], []
    if REDWOOD.is_dir():
        seq = load_sequence(REDWOOD)
        for label, over in (("default", {}), ("information: fixed", {"loop_closure": {"information": "fixed"}}),
                            ("descriptor candidates only", {"loop_closure": {"candidates": "descriptor"}})):
            if quick and label != "default":
                continue
            agent, sec = _run_agent(seq, over)
            rows.append({"config": label, **_row("redwood_livingroom1_211", seq, agent, sec)})
            if label == "default":
                ref = _reference_check(seq, agent)
    else:
        notes.append(f"{REDWOOD} not present: Redwood rows skipped")
    import tempfile

    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    with tempfile.TemporaryDirectory() as tmp:
        frames = 60 if quick else 120
        ds = generate(Path(tmp) / "g", GeneratorConfig.preset("default", agents=1, frames=frames, seed=3))
        seq = load_sequence(next(p for p in sorted(Path(ds).iterdir()) if p.is_dir()))
        agent, sec = _run_agent(seq, {})
        rows.append({"config": "default", **_row(f"generated seed 3 ({frames} frames)", seq, agent, sec)})
    notes.append("ate_no_lc_cm is the same run's tracking-only trajectory (slam.dense.agent.Agent.trajectory_no_lc).")
    if ref:
        notes.append("Reference check (revisit pairs, point-to-plane at 5 cm, 320x240): " + "; ".join(
            f"{r['pair']}: pseudo-GT {r['pseudo_gt_rmse_mm']:.1f} mm / ours {r['ours_rmse_mm']:.1f} mm" for r in ref))
    cols = ["config", "sequence", "frames", "ate_cm", "ate_no_lc_cm", "candidates", "accepted", "descriptor_acc",
            "pose_acc", "rejected_after_opt", "not_applied", "seconds"]
    return {"rows": rows, "columns": cols, "notes": notes, "reference_check": ref}
