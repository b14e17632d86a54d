"""Checks that keep loop closure from making a trajectory worse (used by the agent and by the server).

After each pose-graph optimisation every accepted loop is compared with the optimised poses: a loop the optimum
cannot satisfy (its residual above `residual_max_trans` / `residual_max_deg`) disagrees with the odometry and the
other loops, so it is rejected and the graph solved again, worst loop first. Then the move itself is checked: no
keyframe may move further than the loops' measured disagreement with the current poses can explain
(`max_move_factor` x that disagreement + `max_move_slack`, the disagreement counting a rotation by its lever arm
over the map's extent). An optimisation that fails this is not applied.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels import se3


@dataclass
class LoopResidual:
    index: int  # position in the list that was checked
    trans_m: float
    rot_deg: float


def residual(T_i: np.ndarray, T_j: np.ndarray, T_ij: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) of the measured T_ij against the poses: T_ij⁻¹ · T_i⁻¹ · T_j."""
    E = se3.inverse(T_ij) @ se3.inverse(T_i) @ T_j
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(se3.rotation_angle(E[:3, :3])))


def loop_residuals(poses: dict, loops: list[tuple[int, int, np.ndarray]]) -> list[LoopResidual]:
    """`residual` of every loop, in one array operation over the loops (a long mission's agent checks thousands
    after each optimisation)."""
    if not loops:
        return []
    Ti = np.stack([poses[i] for i, _, _ in loops]).astype(np.float64)
    Tj = np.stack([poses[j] for _, j, _ in loops]).astype(np.float64)
    E = se3.inverse(np.stack([T for _, _, T in loops])) @ se3.inverse(Ti) @ Tj
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(se3.rotation_angle(E[:, :3, :3]))
    return [LoopResidual(n, float(t), float(r)) for n, (t, r) in enumerate(zip(trans, rot))]


def worst_violation(poses: dict, loops: list[tuple[int, int, np.ndarray]], max_trans: float,
                    max_deg: float) -> LoopResidual | None:
    """The loop whose residual exceeds the limits by the largest factor, or None when all fit."""
    worst, score = None, 1.0
    for r in loop_residuals(poses, loops):
        s = max(r.trans_m / max_trans, r.rot_deg / max_deg)
        if s > score:
            worst, score = r, s
    return worst


def extent(poses: dict) -> float:
    """Largest distance of a camera centre from the centres' mean (m): the lever arm of a small rotation."""
    if not poses:
        return 0.0
    c = np.stack([T[:3, 3] for T in poses.values()])
    return float(np.linalg.norm(c - c.mean(0), axis=1).max())


def justified_move(poses: dict, loops: list[tuple[int, int, np.ndarray]], factor: float, slack: float) -> float:
    """How far (m) an optimisation may move a keyframe given the loops' disagreement with `poses`."""
    lever = extent(poses)
    worst = 0.0
    for r in loop_residuals(poses, loops):
        worst = max(worst, r.trans_m + np.radians(r.rot_deg) * lever)
    return factor * worst + slack


def max_move(before: dict, after: dict) -> float:
    """Largest camera-centre displacement (m) between two pose sets over their common keys."""
    keys = [k for k in before if k in after]
    if not keys:
        return 0.0
    return float(max(np.linalg.norm(after[k][:3, 3] - before[k][:3, 3]) for k in keys))
