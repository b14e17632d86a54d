"""Relative pose error (RPE): how wrong the motion between poses `delta` frames apart is (drift per step).

For pairs (i, i + delta) of consecutive matched poses, E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q ground truth and
P the estimate (Sturm et al., TUM RGB-D); the translation error is |t(E)| in metres and the rotation error the
angle of R(E). Equal to `evo_rpe` with `--delta D --delta_unit f` (consecutive pairs). A rigid alignment does
not change RPE; Sim(3) alignment rescales the estimate first (monocular).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError

from .align import PosePairs, alignment, associate_poses, check_align_mode
from .ate import ErrorStats


@dataclass
class RpeResult:
    trans: ErrorStats  # metres
    rot_deg: ErrorStats  # degrees
    errors_trans: np.ndarray  # [P]
    errors_rot_deg: np.ndarray  # [P]
    delta: int
    scale: float
    pairs: PosePairs

    @property
    def rmse(self) -> float:
        return self.trans.rmse

    def to_dict(self) -> dict:
        return {"trans": asdict(self.trans), "rot_deg": asdict(self.rot_deg), "delta": self.delta,
                "pairs": len(self.errors_trans), "scale": self.scale}


def rpe_from_pairs(pairs: PosePairs, *, delta: int = 1, align: str = "none") -> RpeResult:
    """RPE of paired poses over consecutive index pairs (0, d), (d, 2d), ... as evo's default."""
    if int(delta) != delta or delta < 1:
        raise InputError(f"RPE delta must be a positive whole number of frames, got {delta}")
    delta = int(delta)
    align = check_align_mode(align)
    T_est = pairs.T_est
    scale = 1.0
    if align == "sim3":
        S = alignment(pairs.T_gt, pairs.T_est, "sim3")
        T_est = S.apply_to_poses(T_est)
        scale = S.scale
    ids = np.arange(0, len(T_est), delta)
    i, j = ids[:-1], ids[1:]
    if len(i) == 0:
        raise InputError(f"RPE needs at least {delta + 1} matched poses, got {len(T_est)}")
    Q_rel = se3.inverse(pairs.T_gt[i]) @ pairs.T_gt[j]
    P_rel = se3.inverse(T_est[i]) @ T_est[j]
    E = se3.inverse(Q_rel) @ P_rel
    et = np.linalg.norm(E[:, :3, 3], axis=1)
    er = np.degrees(se3.rotation_angle(E[:, :3, :3]))
    return RpeResult(ErrorStats.of(et), ErrorStats.of(er), et, er, delta, scale, pairs)


def rpe(t_gt: np.ndarray, T_gt: np.ndarray, t_est: np.ndarray, T_est: np.ndarray, *, delta: int = 1,
        align: str = "none", max_diff: float = 0.01, offset: float = 0.0, by_index: bool = False) -> RpeResult:
    """RPE of T_world_cam estimates [M, 4, 4] at stamps [M] against ground truth [N, 4, 4] at stamps [N]."""
    pairs = associate_poses(t_gt, T_gt, t_est, T_est, max_diff=max_diff, offset=offset, by_index=by_index)
    return rpe_from_pairs(pairs, delta=delta, align=align)
