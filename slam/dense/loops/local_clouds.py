"""Local maps as point clouds for 3-D loop registration (GRAND-SLAM §III-E registers loops on the submaps' dense
clouds): a window of an agent's keyframes around one keyframe, their depth fused in that keyframe's camera frame
with the agent's current poses, downsampled with normals and FPFH features once (`registration.global_registration`)
and cached; and the route that registers two such windows without an initial guess (`WindowRegistrar.register`).

Frames: a window cloud is in its centre keyframe's camera frame; `T_target_source` of two windows is therefore
T_match_query, the query keyframe's camera in the match keyframe's, as every loop edge.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels import se3

from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.submaps import Keyframe, world_pose


def window_keyframes(keyframes: list[Keyframe], center: Keyframe, radius: int, *, below: int | None = None
                     ) -> list[Keyframe]:
    """`center` and the agent's keyframes whose ids are within `radius` of its id (those that exist, and below id
    `below` when given: two windows of one agent must not share keyframes), centre first."""
    top = len(keyframes) if below is None else min(len(keyframes), below)
    ids = [k for d in range(1, radius + 1) for k in (center.id - d, center.id + d)]
    return [center] + [keyframes[k] for k in ids if 0 <= k < top and keyframes[k] is not center]


def window_points(keyframes: list[Keyframe], gmap: GaussianMap, center: Keyframe, window: list[Keyframe], *,
                  max_depth: float, stride: int = 2) -> np.ndarray:
    """[N, 3] points (metres) of the window's loop-closure copies (every `stride`-th pixel with depth in
    (0, max_depth]) in the centre keyframe's camera frame, placed with the agent's current world poses."""
    T_center = se3.inverse(world_pose(gmap, center))
    parts = []
    for kf in window:
        view = kf.small
        d = view.depth[::stride, ::stride]
        v, u = np.nonzero((d > 0) & (d <= max_depth))
        if not len(u):
            continue
        cam = view.camera
        z = d[v, u].astype(np.float64)
        P = np.stack([(u * stride - cam.cx) / cam.fx * z, (v * stride - cam.cy) / cam.fy * z, z], 1)
        T = T_center @ world_pose(gmap, kf)
        parts.append(P @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(parts) if parts else np.zeros((0, 3))


@dataclass
class CloudOutcome:
    """One window-to-window registration: the pose and its scores, or why there is none."""

    T_match_query: np.ndarray | None  # [4, 4]
    reason: str  # "" when a pose was found
    fitness: float = 0.0
    inlier_rmse: float = float("inf")
    inliers: int = 0
    information: np.ndarray | None = None  # [6, 6], twist order [omega, v]
    n_correspondences: int = 0
    method: str = ""
    time_s: float = 0.0


class WindowRegistrar:
    """Registers keyframe windows of two agents (or two stretches of one agent) without an initial guess, with
    each window's features computed once: a window is cached under (agent, centre keyframe) and rebuilt only
    when it gained keyframes. `stats()` counts windows, registrations and their seconds."""

    def __init__(self, *, radius: int = 4, voxel: float = 0.08, method: str = "auto", min_points: int = 300,
                 min_fitness: float = 0.2, max_rmse: float = 0.06, min_inliers: int = 8, max_cached: int = 512):
        self.radius, self.voxel, self.method = int(radius), float(voxel), method
        self.min_points, self.min_fitness, self.max_rmse = int(min_points), float(min_fitness), float(max_rmse)
        self.min_inliers, self.max_cached = int(min_inliers), int(max_cached)
        self._cache: dict = {}  # (agent, kf id) -> (n keyframes in the window, PreparedCloud or None)
        self.windows_built = 0
        self.registrations = 0
        self.found = 0
        self.prepare_s = 0.0
        self.register_s = 0.0

    def __getstate__(self) -> dict:
        """Checkpoints keep the counters, not the cache (Open3D objects do not pickle; windows are rebuilt)."""
        return {**self.__dict__, "_cache": {}}

    def window(self, key, keyframes: list[Keyframe], gmap: GaussianMap, center: Keyframe, *, max_depth: float,
               below: int | None = None):
        """The PreparedCloud of the window around `center` (None: too few depth points), cached under `key`
        (with `below`: only keyframes with smaller ids, see window_keyframes)."""
        from swarmsplat.registration.global_registration import prepare_cloud

        win = window_keyframes(keyframes, center, self.radius, below=below)
        # The window's current poses are part of the key: a pose-graph optimisation that moved its submaps (or a
        # resumed run, which starts with no cache) rebuilds it, so the cloud never lags the map.
        poses = np.stack([world_pose(gmap, k) for k in win])
        key = (key, tuple(k.id for k in win), np.round(poses, 6).tobytes())
        hit = self._cache.get(key)
        if hit is not None:
            return hit[1]
        t0 = time.perf_counter()
        pts = window_points(keyframes, gmap, center, win, max_depth=max_depth)
        cloud = prepare_cloud(pts, self.voxel, min_points=self.min_points)
        self.prepare_s += time.perf_counter() - t0
        self.windows_built += 1
        if len(self._cache) >= self.max_cached:  # oldest first: dicts keep insertion order
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = (len(win), cloud)
        return cloud

    def register(self, query, match, init: np.ndarray | None = None) -> CloudOutcome:
        """Register two windows (PreparedCloud or None) -> the outcome, gated by fitness and RMSE: by global
        registration, or by ICP alone from `init` (T_match_query [4, 4]) when given."""
        from swarmsplat.registration.global_registration import GlobalResult, global_register, refine

        if query is None or match is None:
            which = "query" if query is None else "match"
            return CloudOutcome(None, f"too few depth points in the {which} window (< {self.min_points} after a "
                                      f"{100 * self.voxel:.0f} cm voxel grid)")
        t0 = time.perf_counter()
        self.registrations += 1
        if init is not None:
            r = GlobalResult(np.asarray(init, dtype=np.float64), True, "icp")
        else:
            r = global_register(query, match, method=self.method, min_inliers=self.min_inliers)
        if not r.found:
            self.register_s += time.perf_counter() - t0
            return CloudOutcome(None, r.reason, inliers=r.inliers, method=r.method, time_s=r.time_s)
        r = refine(query, match, r)
        self.register_s += time.perf_counter() - t0
        out = CloudOutcome(r.T_target_source, "", r.fitness, r.inlier_rmse, r.inliers, r.information,
                           r.n_correspondences, r.method, r.time_s)
        if r.fitness < self.min_fitness:
            out.reason = f"cloud fitness {r.fitness:.3f} < {self.min_fitness}"
        elif r.inlier_rmse > self.max_rmse:
            out.reason = f"cloud inlier RMSE {r.inlier_rmse:.4f} m > {self.max_rmse}"
        else:
            self.found += 1
        return out

    def stats(self) -> dict:
        return {"windows_built": self.windows_built, "registrations": self.registrations, "found": self.found,
                "prepare_s": self.prepare_s, "register_s": self.register_s}
