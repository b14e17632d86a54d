"""One call from two trajectories to every trajectory number we report (what `swarmsplat eval` prints)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import Trajectory

from .align import check_align_mode
from .ate import AteResult, ate
from .rpe import RpeResult, rpe_from_pairs


@dataclass
class TrajectoryEvaluation:
    ate: AteResult
    rpe: RpeResult
    gt: Trajectory
    est: Trajectory
    max_diff: float

    def to_dict(self) -> dict:
        """JSON-ready summary; `ate_rmse`, `rpe_rmse` (metres) and `matched` are the stable top-level keys."""
        a, r = self.ate, self.rpe
        return {
            "ate_rmse": a.rmse,
            "rpe_rmse": r.rmse,
            "matched": a.matched,
            "rpe_rot_rmse_deg": r.rot_deg.rmse,
            "align": a.align,
            "scale": a.transform.scale,
            "alignment_matrix": a.transform.matrix.tolist(),
            "ate": a.to_dict(),
            "rpe": r.to_dict(),
            "n_gt": len(self.gt),
            "n_est": len(self.est),
            "max_diff_s": self.max_diff if self.gt.stamped else None,
            "gt": {"path": str(self.gt.path), "format": self.gt.fmt},
            "est": {"path": str(self.est.path), "format": self.est.fmt},
        }

    def plot(self, path) -> Path:
        """PNG of the aligned estimate over the ground truth, with the per-pose ATE."""
        from swarmsplat.slam.io.plots import plot_trajectories

        a = self.ate
        return plot_trajectories(path, {"agent": self.gt.T_world_cam[:, :3, 3]}, {"agent": a.T_est_aligned[:, :3, 3]},
                                 errors={"agent": a.errors},
                                 title=f"{self.est.path.name}: ATE RMSE {a.rmse:.4f} m ({a.align})")

    def table(self) -> str:
        """A plain-text table: one row per metric with RMSE, mean, median and max, and the unit."""
        a, r = self.ate, self.rpe
        head = (f"{a.matched} of {len(self.est)} estimated poses matched to {len(self.gt)} ground-truth poses; "
                f"alignment {a.align}" + (f" (scale {a.transform.scale:.6f})" if a.align == "sim3" else ""))
        rows = [("ATE", a.stats, "m"), (f"RPE trans (delta {r.delta})", r.trans, "m"),
                (f"RPE rot (delta {r.delta})", r.rot_deg, "deg")]
        w = max(len(n) for n, _, _ in rows)
        lines = [head, f"{'metric':<{w}}  {'rmse':>10}  {'mean':>10}  {'median':>10}  {'max':>10}  unit"]
        for name, s, unit in rows:
            lines.append(f"{name:<{w}}  {s.rmse:>10.6f}  {s.mean:>10.6f}  {s.median:>10.6f}  {s.max:>10.6f}  {unit}")
        return "\n".join(lines)


def evaluate_trajectories(gt: Trajectory, est: Trajectory, *, align: str = "se3", max_diff: float = 0.01,
                          delta: int = 1) -> TrajectoryEvaluation:
    """ATE (after `align`) and RPE over `delta` frames (rescaled when align is sim3) of `est` against `gt`.

    Time-stamped trajectories pair by nearest stamp within `max_diff` s; two unstamped ones (KITTI, .log)
    pair row by row. Mixing the two kinds is refused: there is no way to line them up.
    """
    align = check_align_mode(align)
    if gt.stamped != est.stamped:
        stamped, bare = (gt, est) if gt.stamped else (est, gt)
        raise InputError(f"{bare.path} ({bare.fmt}) has no timestamps but {stamped.path} ({stamped.fmt}) has; "
                         f"both trajectories need timestamps, or neither")
    a = ate(gt.timestamps, gt.T_world_cam, est.timestamps, est.T_world_cam, align=align, max_diff=max_diff,
            by_index=not gt.stamped)
    r = rpe_from_pairs(a.pairs, delta=delta, align="sim3" if align == "sim3" else "none")
    if not np.isfinite(a.rmse) or not np.isfinite(r.rmse):
        raise InputError("trajectory errors are not finite; check both files for degenerate poses")
    return TrajectoryEvaluation(a, r, gt, est, max_diff)
