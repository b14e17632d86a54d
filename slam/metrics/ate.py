"""Absolute trajectory error (ATE): RMSE of position differences after aligning the estimate to ground truth.

Per agent, each estimate is aligned on its own; `ate_multi` also reports the team in one frame: all agents'
matched poses stacked and aligned by ONE transform, which is what a shared map needs to be right.
Numbers equal evo's `evo_ape ... -a` (SE(3)) and `-as` (Sim(3)) with the same association tolerance.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Mapping

import numpy as np

from swarmsplat.kernels.errors import InputError

from .align import PosePairs, Sim3, alignment, associate_poses


@dataclass
class ErrorStats:
    """Summary statistics of a per-pose error array (the names and definitions evo uses)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float

    @staticmethod
    def of(errors: np.ndarray) -> "ErrorStats":
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            raise InputError("no errors to summarise (no matched poses)")
        return ErrorStats(rmse=float(np.sqrt(np.mean(e**2))), mean=float(e.mean()), median=float(np.median(e)),
                          std=float(e.std()), min=float(e.min()), max=float(e.max()), sse=float(np.sum(e**2)))


@dataclass
class AteResult:
    """ATE of one trajectory (or of several stacked): translation errors in metres after `align`."""

    stats: ErrorStats
    errors: np.ndarray  # [K] metres
    align: str
    transform: Sim3  # estimate -> ground-truth frame
    pairs: PosePairs
    T_est_aligned: np.ndarray = field(repr=False, default=None)  # [K, 4, 4]

    @property
    def rmse(self) -> float:
        return self.stats.rmse

    @property
    def matched(self) -> int:
        return self.pairs.matched

    def to_dict(self) -> dict:
        return {**asdict(self.stats), "matched": self.matched, "align": self.align, "scale": self.transform.scale}


def ate_from_pairs(pairs: PosePairs, align: str = "se3") -> AteResult:
    """ATE of already paired poses."""
    S = alignment(pairs.T_gt, pairs.T_est, align)
    T_al = S.apply_to_poses(pairs.T_est)
    err = np.linalg.norm(T_al[:, :3, 3] - pairs.T_gt[:, :3, 3], axis=1)
    return AteResult(ErrorStats.of(err), err, align, S, pairs, T_al)


def ate(t_gt: np.ndarray, T_gt: np.ndarray, t_est: np.ndarray, T_est: np.ndarray, *, align: str = "se3",
        max_diff: float = 0.01, offset: float = 0.0, by_index: bool = False) -> AteResult:
    """ATE RMSE of T_world_cam estimates [M, 4, 4] at stamps [M] against ground truth [N, 4, 4] at stamps [N].

    align: "se3" (rigid Umeyama), "sim3" (with scale, for monocular estimates) or "none".
    max_diff: association tolerance in seconds; by_index pairs row by row (KITTI / .log files).
    """
    pairs = associate_poses(t_gt, T_gt, t_est, T_est, max_diff=max_diff, offset=offset, by_index=by_index)
    return ate_from_pairs(pairs, align)


@dataclass
class MultiAteResult:
    per_agent: dict[str, AteResult]
    joint: AteResult  # all agents in one frame, one alignment

    def to_dict(self) -> dict:
        return {"per_agent": {k: v.to_dict() for k, v in self.per_agent.items()}, "joint": self.joint.to_dict()}


def ate_multi(gt: Mapping[str, tuple[np.ndarray, np.ndarray]], est: Mapping[str, tuple[np.ndarray, np.ndarray]], *,
              align: str = "se3", max_diff: float = 0.01, by_index: bool = False) -> MultiAteResult:
    """ATE per agent and for the whole team in one frame.

    gt, est: agent name -> (timestamps [N], T_world_cam [N, 4, 4]); every estimated agent needs ground truth.
    The estimates of all agents must live in one common world frame for the joint number to mean anything.
    An agent with too few (or collinear) poses to be aligned on its own is scored under the joint alignment; its
    result then has align == "joint".
    """
    missing = sorted(set(est) - set(gt))
    if missing:
        raise InputError(f"no ground truth for agent(s) {', '.join(missing)}")
    if not est:
        raise InputError("no estimated trajectories given")
    per_agent, pairs_of, own_failed = {}, {}, []
    for name in est:
        pairs_of[name] = pairs = associate_poses(*gt[name], *est[name], max_diff=max_diff, by_index=by_index)
        try:
            per_agent[name] = ate_from_pairs(pairs, align)
        except InputError:  # too few / collinear poses to align this agent alone (e.g. 2 frames of a split)
            own_failed.append(name)
    all_pairs = list(pairs_of.values())
    stacked = PosePairs(
        timestamps=np.concatenate([p.timestamps for p in all_pairs]),
        T_gt=np.concatenate([p.T_gt for p in all_pairs]),
        T_est=np.concatenate([p.T_est for p in all_pairs]),
        n_gt=sum(p.n_gt for p in all_pairs),
        n_est=sum(p.n_est for p in all_pairs),
    )
    joint = ate_from_pairs(stacked, align)  # raises if even the stacked poses cannot be aligned
    for name in own_failed:  # such an agent is scored under the team's one alignment (align = "joint")
        p = pairs_of[name]
        T_al = joint.transform.apply_to_poses(p.T_est)
        err = np.linalg.norm(T_al[:, :3, 3] - p.T_gt[:, :3, 3], axis=1)
        per_agent[name] = AteResult(ErrorStats.of(err), err, "joint", joint.transform, p, T_al)
    return MultiAteResult({n: per_agent[n] for n in est}, joint)
