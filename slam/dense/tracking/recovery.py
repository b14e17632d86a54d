"""Recovery of a frame the coarse stage lost (large motion: skipped frames, a quick turn).

When the coarse frame-to-frame odometry fails its own checks (no convergence, or a step longer than
`coarse_max_motion`), the tracker would chain constant velocity, which is wrong exactly when the motion was large.
Two retries, cheapest first, each a learned start (slam.dense.loops.learned_coarse: XFeat + LighterGlue matches
lifted with depth, RANSAC rigid fit; no initial pose needed) refined by the same coarse odometry and gated by the
same checks:

1. `retry`: the frame against the previous frame.
2. `relocalise`: the frame against the current submap's keyframes (newest first, at most
   `recovery_max_keyframes`), so a frame that lost the previous one is placed against the map's anchors rather
   than chained from a bad pose.

Nothing here runs unless the coarse stage failed: on sequences where it never fails the tracker is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.slam.config import TrackingConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.loops.learned_coarse import coarse_guess_from_pair
from swarmsplat.slam.dense.rgbd_registration import Registration, coarse_odometry


@dataclass
class RecoveryCounts:
    """Per run: frames whose coarse stage failed, those recovery was tried on, recovered by the retry against
    the previous frame, and re-localised against a keyframe of the current submap (metrics.json
    `tracking_recoveries`)."""

    coarse_failed: int = 0  # frames whose coarse stage failed its checks (counted with the recovery off too)
    attempted: int = 0
    succeeded: int = 0  # retry + relocalised
    retried: int = 0
    relocalised: int = 0
    frames: list[int] = field(default_factory=list)  # tracker frame counter of each recovered frame

    def as_dict(self) -> dict:
        return {"coarse_failed": self.coarse_failed, "attempted": self.attempted, "succeeded": self.succeeded, "retried": self.retried,
                "relocalised": self.relocalised}


def coarse_passes(r: Registration | None, cfg: TrackingConfig) -> bool:
    """The coarse stage's own checks: converged, and a step no longer than `coarse_max_motion` (m)."""
    return (r is not None and r.success
            and float(np.linalg.norm(r.T_target_source[:3, 3])) <= cfg.coarse_max_motion)


def learned_register(source: RGBD, target: RGBD, cfg: TrackingConfig, *, max_depth: float,
                     max_motion: float) -> tuple[np.ndarray, Registration | None] | None:
    """T_target_source [4, 4] between two frames of the same camera from a learned start (XFeat + depth +
    RANSAC), refined by the coarse odometry, and that registration; None when no start is found or it steps
    further than `max_motion` (m). When the odometry fails from the start, or moves it by more than
    `recovery_max_disagreement` (it slid into another minimum), the start itself is returned with no
    registration: the frame-to-model refinement and the failed-odometry covariance take it from there."""
    T0, _ = coarse_guess_from_pair(source.color, source.depth, target.color, target.depth, source.camera,
                                   top_k=cfg.recovery_top_k, max_side=source.camera.width, depth_max=max_depth)
    if T0 is None or float(np.linalg.norm(T0[:3, 3])) > max_motion:
        return None
    r = coarse_odometry(source, target, T0, max_depth=max_depth)
    if (r.success and float(np.linalg.norm(r.T_target_source[:3, 3])) <= max_motion
            and float(np.linalg.norm(r.T_target_source[:3, 3] - T0[:3, 3])) <= cfg.recovery_max_disagreement):
        return r.T_target_source, r
    return T0, None


def recover(frame: RGBD, prev: RGBD, prev_pose: np.ndarray, anchors: list[tuple[RGBD, np.ndarray]],
            cfg: TrackingConfig, counts: RecoveryCounts, *, max_depth: float
            ) -> tuple[np.ndarray, Registration | None, str] | None:
    """(T_local_cam [4, 4] of `frame`, the odometry registration it came from or None, "retry" | "relocalised")
    after a failed coarse stage; None when neither the retry nor the re-localisation finds it. `frame` and `prev`
    at coarse_max_width; `anchors`: (keyframe at coarse_max_width, its T_local_cam) of the current submap, oldest
    first."""
    counts.attempted += 1
    found = learned_register(frame, prev, cfg, max_depth=max_depth, max_motion=cfg.recovery_max_motion)
    if found is not None:
        counts.retried += 1
        counts.succeeded += 1
        return prev_pose @ found[0], found[1], "retry"
    for kf, T_local_kf in reversed(anchors[max(0, len(anchors) - cfg.recovery_max_keyframes):]):
        found = learned_register(frame, kf, cfg, max_depth=max_depth, max_motion=cfg.recovery_max_motion)
        if found is not None:
            counts.relocalised += 1
            counts.succeeded += 1
            return T_local_kf @ found[0], found[1], "relocalised"
    return None
