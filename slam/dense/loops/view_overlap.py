"""How much two keyframe views share at given poses: the view overlap of reprojected depth, and the pose candidates
of a keyframe ranked by it (GRAND-SLAM eq. 6's initial guess: distance, viewing angle, then reprojected depth)."""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3

from swarmsplat.slam.config import LoopClosureConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.submaps import Keyframe


def nearest_by_overlap(query: RGBD, T_q: np.ndarray, poses: np.ndarray, others: list, payloads: list,
                       cfg: LoopClosureConfig) -> list:
    """Pose candidates of the query (its view `query`, its pose T_q [4, 4]) among keyframes at `poses` [M, 4, 4]
    (the same frame as T_q) with views `others` [M]: those within cfg.pose_max_distance and
    cfg.pose_max_angle_deg, as [(view overlap, payload)], best overlap first (ties in the given order). The pose
    test is one array operation over all M; the overlap (an image decode each) is computed for the closest
    cfg.pose_max_checked only (distance plus angle, 1 m per radian), since revisits pile up keyframes at one
    place: a search costs about the same on the tenth lap as on the first."""
    if not len(others):
        return []
    T_oq = se3.inverse(np.asarray(poses, dtype=np.float64)) @ T_q  # [M, 4, 4]
    dist = np.linalg.norm(T_oq[:, :3, 3], axis=1)
    angle = se3.rotation_angle(T_oq[:, :3, :3])
    ok = np.nonzero((dist <= cfg.pose_max_distance) & (np.degrees(angle) <= cfg.pose_max_angle_deg))[0]
    closest = ok[np.argsort(dist[ok] + angle[ok], kind="stable")][: cfg.pose_max_checked]
    near = [(view_overlap(query, others[i], T_oq[i]), int(i)) for i in closest]
    near.sort(key=lambda s: (-s[0], s[1]))
    return [(ov, payloads[i]) for ov, i in near]


def keyframe_poses(gmap: GaussianMap, keyframes: list[Keyframe]) -> np.ndarray:
    """[M, 4, 4] world poses of `keyframes` (world_pose for each, as one batched product)."""
    if not keyframes:
        return np.zeros((0, 4, 4))
    sub = np.stack([gmap.submaps[k.submap_id].T_world_local for k in keyframes])
    return sub @ np.stack([k.T_local for k in keyframes])


def view_overlap(query: RGBD, match: RGBD, T_match_query: np.ndarray, *, stride: int = 4,
                 depth_tolerance: float = 0.1) -> float:
    """Fraction of the query's valid depth pixels (every `stride`-th) that land inside the match image in front
    of its camera with a depth within `depth_tolerance` (relative) of the match's depth there."""
    d = query.depth[::stride, ::stride]
    cam = query.camera
    v, u = np.nonzero(d > 0)
    if len(u) == 0:
        return 0.0
    z = d[v, u].astype(np.float64)
    x = ((u * stride - cam.cx) / cam.fx) * z
    y = ((v * stride - cam.cy) / cam.fy) * z
    p = np.stack([x, y, z], 1) @ T_match_query[:3, :3].T + T_match_query[:3, 3]
    mc = match.camera
    front = p[:, 2] > 1e-3
    zu = np.where(front, p[:, 2], 1.0)
    uu = np.round(mc.fx * p[:, 0] / zu + mc.cx).astype(np.int64)
    vv = np.round(mc.fy * p[:, 1] / zu + mc.cy).astype(np.int64)
    inside = front & (uu >= 0) & (uu < mc.width) & (vv >= 0) & (vv < mc.height)
    dm = np.zeros(len(z))
    dm[inside] = match.depth[vv[inside], uu[inside]]
    ok = inside & (dm > 0) & (np.abs(dm - p[:, 2]) < depth_tolerance * p[:, 2])
    return float(ok.sum()) / len(z)
