"""Intra-agent loop closures (GRAND-SLAM §III-D–E): descriptor candidates, RGB-D registration with fitness / RMSE
gates, pose-graph optimisation over keyframe poses, and submaps moved to the optimised frames (eqs. 14–15).

Every candidate is recorded with the reason it was accepted or rejected (`LoopCloser.log`).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np

from kernels import se3
from kernels.errors import InputError

from .config import LoopClosureConfig
from .gaussian_map import GaussianMap
from .odometry_adapter import register_loop
from .submaps import Keyframe, world_pose


def _make_recognizer(cfg: LoopClosureConfig):
    """The keyframe descriptor named in the config, from registration.place_recognition."""
    from registration.place_recognition import make_recognizer

    name = "thumbnail" if cfg.descriptor == "auto" else cfg.descriptor
    if name in ("bow", "vlad") and not cfg.vocabulary:
        raise InputError(f"loop_closure.descriptor {name!r} needs loop_closure.vocabulary (a .npz vocabulary file)")
    return make_recognizer(name, checkpoint=cfg.vocabulary if name != "thumbnail" else None)


@dataclass
class LoopCandidate:
    query_kf: int
    match_kf: int
    query_frame: int
    match_frame: int
    similarity: float
    accepted: bool = False
    reason: str = ""
    fitness: float = 0.0
    inlier_rmse: float = float("inf")
    correction_m: float = 0.0


@dataclass
class Edge:
    """A relative-pose constraint between two keyframes of one agent (odometry or an accepted loop)."""

    i: int  # keyframe ids
    j: int
    T_ij: np.ndarray  # [4, 4] pose of j in i's camera frame
    sigma_rot: float
    sigma_trans: float


class LoopCloser:
    def __init__(self, cfg: LoopClosureConfig, *, max_depth: float = 10.0):
        self.cfg = cfg
        self.max_depth = max_depth
        self.odometry: list[Edge] = []
        self.loops: list[Edge] = []
        self.log: list[LoopCandidate] = []
        self.optimisations = 0
        self._recognizer = _make_recognizer(cfg)

    # ---- the keyframe chain ---------------------------------------------------------------------------------

    def add_keyframe(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap) -> None:
        """Record the tracking constraint between the previous keyframe and `kf`, as tracked now."""
        kf.descriptor = self._recognizer.describe(kf.small.color)
        if kf.id > 0:
            prev = keyframes[kf.id - 1]
            T = se3.inverse(world_pose(gmap, prev)) @ world_pose(gmap, kf)
            self.odometry.append(Edge(prev.id, kf.id, T, self.cfg.odometry_sigma_rot, self.cfg.odometry_sigma_trans))

    # ---- detection and verification ------------------------------------------------------------------------

    def candidates(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap) -> list[LoopCandidate]:
        """Top-k keyframes of earlier submaps by cosine similarity above τ_sim, at least Δ_min frames apart."""
        cfg = self.cfg
        T_q = world_pose(gmap, kf)
        scored = []
        for other in keyframes:
            if other.submap_id == kf.submap_id or other.descriptor is None:
                continue
            if kf.frame_index - other.frame_index < cfg.min_index_gap:
                continue
            if cfg.min_baseline > 0 and np.linalg.norm(world_pose(gmap, other)[:3, 3] - T_q[:3, 3]) < cfg.min_baseline:
                continue
            scored.append((float(np.dot(kf.descriptor, other.descriptor)), other))
        scored.sort(key=lambda s: -s[0])
        out = []
        for sim, other in scored[: cfg.top_k]:
            c = LoopCandidate(kf.id, other.id, kf.frame_index, other.frame_index, sim)
            if sim < cfg.tau_sim:
                c.reason = f"similarity {sim:.3f} < tau_sim {cfg.tau_sim}"
                self.log.append(c)
                continue
            out.append(c)
        return out

    def verify(self, c: LoopCandidate, keyframes: list[Keyframe], gmap: GaussianMap) -> LoopCandidate:
        """Register query (source) to match (target) from the tracked guess (eq. 6), then apply the gates."""
        cfg = self.cfg
        q, j = keyframes[c.query_kf], keyframes[c.match_kf]
        T_init = se3.inverse(world_pose(gmap, j)) @ world_pose(gmap, q)  # eq. 6: T_j^-1 T_q
        r = register_loop(q.small, j.small, T_init, max_distance=cfg.icp_max_distance, min_fitness=cfg.fitness_min,
                          max_rmse=cfg.rmse_max, max_depth=self.max_depth)
        c.fitness, c.inlier_rmse = r.fitness, r.inlier_rmse
        c.correction_m = float(np.linalg.norm((se3.inverse(T_init) @ r.T_target_source)[:3, 3]))
        if r.fitness <= cfg.fitness_min:
            c.reason = f"fitness {r.fitness:.3f} <= tau_f {cfg.fitness_min}"
        elif r.inlier_rmse >= cfg.rmse_max:
            c.reason = f"inlier RMSE {r.inlier_rmse:.4f} m >= tau_rho {cfg.rmse_max}"
        elif not r.success:
            c.reason = f"registration failed: {r.reason}"
        elif c.correction_m > cfg.max_correction:
            c.reason = f"correction {c.correction_m:.3f} m > max_correction {cfg.max_correction}"
        else:
            c.accepted = True
            c.reason = "accepted"
            self.loops.append(Edge(j.id, q.id, r.T_target_source, cfg.odometry_sigma_rot, cfg.odometry_sigma_trans))
        self.log.append(c)
        return c

    def detect(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap) -> list[LoopCandidate]:
        """Candidates for `kf`, each verified; returns the accepted ones."""
        return [c for c in (self.verify(c, keyframes, gmap) for c in self.candidates(kf, keyframes, gmap))
                if c.accepted]

    # ---- optimisation ------------------------------------------------------------------------------------

    def optimise(self, keyframes: list[Keyframe], gmap: GaussianMap) -> dict:
        """Pose-graph optimisation over keyframe poses, then every submap moved rigidly to the optimised pose of
        its first keyframe (eqs. 14–15; keyframes and Gaussians follow their submap)."""
        initial = {kf.id: world_pose(gmap, kf) for kf in keyframes}
        optimised = optimise_pose_graph(initial, self.odometry, self.loops, fixed=keyframes[0].id)
        moved = []
        for s in gmap.submaps:
            if not s.keyframe_ids:
                continue
            first = keyframes[s.keyframe_ids[0]]
            T_new = optimised[first.id] @ se3.inverse(first.T_local_cam)
            D = T_new @ se3.inverse(s.T_world_local)
            gmap.transform_submap(s, D)
            moved.append(float(np.linalg.norm(D[:3, 3])))
        self.optimisations += 1
        return {"submaps_moved": len(moved), "max_shift_m": max(moved, default=0.0)}

    def log_rows(self) -> list[dict]:
        return [asdict(c) for c in self.log]


def optimise_pose_graph(initial: dict[int, np.ndarray], odometry: list[Edge], loops: list[Edge], *,
                        fixed: int) -> dict[int, np.ndarray]:
    """Levenberg–Marquardt over keyframe poses (eq. 13) with `graph/`: tracking and loop edges as relative-pose
    constraints, information diag(1/sigma^2) in twist order [omega, v]; the graph anchors its first pose (the
    first keyframe, `fixed`)."""
    from graph.formulations import build_problem
    from graph.pose_graph import PoseGraph
    from graph.solvers import solve

    from kernels.errors import SwarmsplatError

    g = PoseGraph()
    for k in sorted(initial):
        g.add_pose(k, initial[k])

    def info(e: Edge) -> np.ndarray:
        return np.diag([1.0 / e.sigma_rot**2] * 3 + [1.0 / e.sigma_trans**2] * 3)

    for e in odometry:
        g.add_odometry(e.i, e.j, e.T_ij, info(e))
    for e in loops:
        g.add_loop(e.i, e.j, e.T_ij, info(e))
    try:
        res = solve(build_problem(g, "base"), "lm")
    except (SwarmsplatError, RuntimeError) as err:  # an indeterminate system: keep the tracked poses
        warnings.warn(f"pose-graph optimisation failed ({err}); poses left as tracked", stacklevel=2)
        return dict(initial)
    out = {k: np.asarray(res.poses[k], dtype=np.float64) for k in initial}
    # The graph anchors each component at its own choice of pose; re-anchor at `fixed` so that frame stays put.
    D = initial[fixed] @ np.linalg.inv(out[fixed])
    return {k: D @ T for k, T in out.items()}
