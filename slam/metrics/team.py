"""Team evaluation: every agent's ATE/RPE on its own, and the team's ATE in one frame (one alignment for all).

Files are found by agent name: ground truth from a dataset root (`<agent>/groundtruth.txt`, as our format and
`dataset.yaml` lay it out) or a folder of `<agent>.txt` files; estimates from `<agent>.txt` / `.tum` files or
`<agent>/trajectory.txt` in the results folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import Trajectory, read_trajectory

from .align import PosePairs, check_align_mode
from .ate import AteResult, ErrorStats, ate_from_pairs
from .evaluate import TrajectoryEvaluation, evaluate_trajectories

_EST_NAMES = ("{a}.txt", "{a}.tum", "{a}.csv", "{a}.log", "{a}/trajectory.txt", "{a}/trajectory.tum")


@dataclass
class TeamEvaluation:
    per_agent: dict[str, TrajectoryEvaluation]
    joint: AteResult  # all agents' matched poses, one alignment
    rpe_trans: ErrorStats  # every agent's RPE pairs pooled
    rpe_rot_deg: ErrorStats
    missing: list[str]  # agents with ground truth but no estimate

    def to_dict(self) -> dict:
        """JSON-ready; the top-level `ate_rmse` is the team's (one frame), `rpe_rmse` pools all agents' pairs."""
        return {
            "ate_rmse": self.joint.rmse,
            "rpe_rmse": self.rpe_trans.rmse,
            "matched": self.joint.matched,
            "rpe_rot_rmse_deg": self.rpe_rot_deg.rmse,
            "align": self.joint.align,
            "scale": self.joint.transform.scale,
            "alignment_matrix": self.joint.transform.matrix.tolist(),
            "joint": self.joint.to_dict(),
            "per_agent": {k: v.to_dict() for k, v in self.per_agent.items()},
            "missing_agents": self.missing,
        }

    def plot(self, path) -> Path:
        """PNG of every agent moved by the ONE team alignment over its ground truth, with per-pose errors."""
        from swarmsplat.slam.io.plots import plot_trajectories

        S = self.joint.transform
        est = {k: S.apply_to_poses(v.ate.pairs.T_est)[:, :3, 3] for k, v in self.per_agent.items()}
        gt = {k: v.gt.T_world_cam[:, :3, 3] for k, v in self.per_agent.items()}
        errs = {k: np.linalg.norm(est[k] - v.ate.pairs.T_gt[:, :3, 3], axis=1) for k, v in self.per_agent.items()}
        return plot_trajectories(path, gt, est, errors=errs,
                                 title=f"team: ATE RMSE {self.joint.rmse:.4f} m ({self.joint.align}, one frame)")

    def table(self) -> str:
        rows = [(f"ATE {k}", v.ate.stats, "m") for k, v in self.per_agent.items()]
        rows.append(("ATE team (one frame)", self.joint.stats, "m"))
        rows += [(f"RPE trans {k}", v.rpe.trans, "m") for k, v in self.per_agent.items()]
        rows.append(("RPE trans team", self.rpe_trans, "m"))
        w = max(len(n) for n, _, _ in rows)
        head = (f"{len(self.per_agent)} agents, {self.joint.matched} matched poses; alignment {self.joint.align}"
                + (f"; no estimate for {', '.join(self.missing)}" if self.missing else ""))
        lines = [head, f"{'metric':<{w}}  {'rmse':>10}  {'mean':>10}  {'median':>10}  {'max':>10}  unit"]
        for name, s, unit in rows:
            lines.append(f"{name:<{w}}  {s.rmse:>10.6f}  {s.mean:>10.6f}  {s.median:>10.6f}  {s.max:>10.6f}  {unit}")
        return "\n".join(lines)


def evaluate_team(gt: Mapping[str, Trajectory], est: Mapping[str, Trajectory], *, align: str = "se3",
                  max_diff: float = 0.01, delta: int = 1) -> TeamEvaluation:
    """Per-agent evaluations plus the team ATE; every estimated agent needs ground truth, agents without an
    estimate are listed in `missing`."""
    align = check_align_mode(align)
    names = [a for a in gt if a in est]
    extra = sorted(set(est) - set(gt))
    if extra:
        raise InputError(f"no ground truth for agent(s) {', '.join(extra)}")
    if not names:
        raise InputError("no agent has both a ground-truth and an estimated trajectory")
    per = {a: evaluate_trajectories(gt[a], est[a], align=align, max_diff=max_diff, delta=delta) for a in names}
    pairs = [per[a].ate.pairs for a in names]
    stacked = PosePairs(np.concatenate([p.timestamps for p in pairs]), np.concatenate([p.T_gt for p in pairs]),
                        np.concatenate([p.T_est for p in pairs]), sum(p.n_gt for p in pairs), sum(p.n_est for p in pairs))
    joint = ate_from_pairs(stacked, align)
    rt = np.concatenate([per[a].rpe.errors_trans for a in names])
    rr = np.concatenate([per[a].rpe.errors_rot_deg for a in names])
    return TeamEvaluation(per, joint, ErrorStats.of(rt), ErrorStats.of(rr), [a for a in gt if a not in est])


def find_team_trajectories(gt_dir: str | Path, est_dir: str | Path, fmt: str = "auto"
                           ) -> tuple[dict[str, Trajectory], dict[str, Trajectory]]:
    """Read ground truth and estimates for every agent found under the two folders (see module docstring)."""
    import yaml

    gt_dir, est_dir = Path(gt_dir), Path(est_dir)
    for d in (gt_dir, est_dir):
        if not d.is_dir():
            raise InputError(f"folder not found: {d}")
    gt_files: dict[str, Path] = {}
    meta = gt_dir / "dataset.yaml"
    if meta.is_file():
        agents = (yaml.safe_load(meta.read_text()) or {}).get("agents") or []
        gt_files = {str(a): gt_dir / str(a) / "groundtruth.txt" for a in agents if (gt_dir / str(a) / "groundtruth.txt").is_file()}
    if not gt_files:
        gt_files = {d.name: d / "groundtruth.txt" for d in sorted(gt_dir.iterdir()) if (d / "groundtruth.txt").is_file()}
    if not gt_files:
        gt_files = {f.stem: f for f in sorted(gt_dir.iterdir())
                    if f.is_file() and f.suffix.lower() in (".txt", ".tum", ".csv", ".log")}
    if not gt_files:
        raise InputError(f"{gt_dir}: no ground truth found (dataset folders with groundtruth.txt, or <agent>.txt files)")
    gt, est = {}, {}
    for a, f in gt_files.items():
        hit = next((est_dir / p.format(a=a) for p in _EST_NAMES if (est_dir / p.format(a=a)).is_file()), None)
        if hit is None:
            continue
        gt[a] = read_trajectory(f, "auto" if f.name == "groundtruth.txt" else fmt)
        est[a] = read_trajectory(hit, fmt)
    missing = [a for a in gt_files if a not in est]
    if not est:
        raise InputError(f"{est_dir}: no estimate for any of the agents {', '.join(gt_files)} "
                         f"(expected files named <agent>.txt)")
    for a in missing:  # keep them visible in the report
        gt[a] = read_trajectory(gt_files[a], "auto" if gt_files[a].name == "groundtruth.txt" else fmt)
    return gt, est
