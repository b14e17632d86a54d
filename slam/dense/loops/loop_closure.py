"""Intra-agent loop closures (GRAND-SLAM §III-D–E): descriptor candidates, RGB-D registration with fitness / RMSE
gates, pose-graph optimisation over keyframe poses, and submaps moved to the optimised frames (eqs. 14–15).

Every candidate is recorded with the reason it was accepted or rejected (`LoopCloser.log`).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError

from . import loop_check
from swarmsplat.slam.config import LoopClosureConfig
from .incremental import IncrementalGraph
from .edge_information import (InformationModel, fixed_information, information, registration_covariance,
                               step_covariances, window_covariance)
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.rgbd_registration import register_loop
from swarmsplat.slam.dense.submaps import Keyframe, world_pose
from .view_overlap import keyframe_poses, nearest_by_overlap, view_overlap


def _make_recognizer(cfg: LoopClosureConfig, image_side: int | None = None):
    """The keyframe descriptor named in the config, from registration.place_recognition. 'auto' is xfeat-vlad
    with the shipped vocabulary, or the thumbnail where XFeat cannot run (not installed, or keyframe copies of
    fewer than 32 pixels a side: `image_side`, the smaller side)."""
    from swarmsplat.registration.place_recognition import GENERIC, make_recognizer

    name = cfg.descriptor
    if name == "auto":
        from swarmsplat.registration.pair import xfeat

        from swarmsplat.registration.images import MIN_SIDE

        name = "xfeat-vlad" if xfeat.available() and (image_side is None or image_side >= MIN_SIDE) else "thumbnail"
    if cfg.vocabulary == "train" and name != "xfeat-vlad":
        raise InputError(f"loop_closure.vocabulary 'train' is for descriptor xfeat-vlad, not {name!r}")
    if name == "xfeat-vlad":  # the shipped vocabulary, a file, or untrained: LoopCloser trains it ('train')
        return make_recognizer(name, checkpoint={None: GENERIC, "train": None}.get(cfg.vocabulary, cfg.vocabulary))
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
    source: str = "descriptor"  # "descriptor" (place recognition) or "pose" (tracked poses' view overlap)
    overlap: float = float("nan")  # view overlap of the tracked poses (pose candidates)
    route: str = "image"  # "image": keyframe registration; "cloud": the two keyframes' local maps (cloud_route)
    render_covisible: float = float("nan")  # verification by rendering (cloud route; NaN: not run)
    render_agree: float = float("nan")
    render_violate: float = float("nan")
    render_photometric: float = float("nan")


@dataclass
class Edge:
    """A relative-pose constraint between two keyframes of one agent (odometry or an accepted loop)."""

    i: int  # keyframe ids
    j: int
    T_ij: np.ndarray  # [4, 4] pose of j in i's camera frame
    info: np.ndarray  # [6, 6] information, twist order [omega, v], in j's tangent space (GTSAM BetweenFactor)
    candidate: LoopCandidate | None = None  # loops: the log entry, updated when the loop is rejected later
    rejected: bool = False
    applied: bool = False  # part of an optimisation that was applied


class LoopCloser:
    def __init__(self, cfg: LoopClosureConfig, *, max_depth: float = 10.0):
        self.cfg = cfg
        self.max_depth = max_depth
        self.odometry: list[Edge] = []
        self.loops: list[Edge] = []
        self.log: list[LoopCandidate] = []
        self.optimisations = 0
        self.not_applied = 0  # optimisations whose move was not justified by the loops
        # The last applied optimum: keyframe id -> T_world_cam. Submaps move rigidly with their first keyframe
        # (eq. 14); a submap's later keyframes keep their own optimised poses here (Agent.trajectory per_keyframe).
        self.optimum: dict[int, np.ndarray] = {}
        self._graph: IncrementalGraph | None = None  # the pose graph iSAM2 keeps (solver 'incremental')
        self.model = InformationModel(n_eff=cfg.information_points)
        # 'auto' is decided on the first keyframe, whose size it needs; a named descriptor is checked now.
        self._recognizer = None if cfg.descriptor == "auto" else _make_recognizer(cfg)
        self._pending: dict[int, np.ndarray] = {}  # xfeat-vlad: local descriptors of keyframes awaiting the vocabulary
        self.clouds = None  # the cloud route's WindowRegistrar, made on first use
        self.cloud_tries: dict[int, int] = {}  # query keyframe id -> candidates that took the cloud route

    def __setstate__(self, state: dict) -> None:  # checkpoints from before the optimum was kept
        state.setdefault("optimum", {})
        self.__dict__.update(state)

    def budget(self) -> dict:
        """The candidates verified per keyframe at most (top_k descriptor ones, pose_top_k pose ones) and the
        similarity gate (None: none): what bounds loop closure's cost per keyframe."""
        c = self.cfg
        return {"descriptor_per_keyframe": c.top_k if c.candidates != "pose" else 0,
                "pose_per_keyframe": c.pose_top_k if c.candidates != "descriptor" else 0, "tau_sim": c.tau_sim}

    @property
    def active_loops(self) -> list[Edge]:
        return [e for e in self.loops if not e.rejected]

    # ---- the keyframe chain ---------------------------------------------------------------------------------

    def _describe(self, kf: Keyframe, keyframes: list[Keyframe]) -> None:
        """kf.descriptor from the configured recogniser, of the keyframe's view at `descriptor_width` (its
        mapping-resolution copy downsampled, while it has one; else the loop-closure copy). An xfeat-vlad recogniser
        with vocabulary 'train' trains it from the first `vocabulary_keyframes` keyframes (k-means over their XFeat
        descriptors), which are described then; until then they have no descriptor (no descriptor candidates)."""
        view = kf.map_rgbd if kf.map_rgbd is not None and kf.map_rgbd.camera.width > kf.small.camera.width else kf.small
        color = view.resized(self.cfg.descriptor_width).color if view.camera.width > self.cfg.descriptor_width \
            else view.color
        if self._recognizer is None:
            self._recognizer = _make_recognizer(self.cfg, min(color.shape[:2]))
        rec = self._recognizer
        if getattr(rec, "trained", True):
            kf.descriptor = rec.describe(color)
            return
        self._pending[kf.id] = rec._local(color)
        if len(self._pending) >= self.cfg.vocabulary_keyframes and \
                sum(len(x) for x in self._pending.values()) >= rec.n_clusters:
            rec.fit_local(list(self._pending.values()))
            by_id = {k.id: k for k in keyframes}
            by_id[kf.id] = kf
            for i, x in self._pending.items():
                by_id[i].descriptor = rec.describe_local(x)
            self._pending = {}

    def add_keyframe(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap,
                     odometry_info: np.ndarray | None = None) -> None:
        """Record the tracking constraint between the previous keyframe and `kf`, as tracked now, with the
        tracker's information (`odometry_info`, slam.dense.loops.edge_information.OdometryChain) or the fixed sigmas."""
        self._describe(kf, keyframes)
        if kf.id > 0:
            prev = keyframes[kf.id - 1]
            if prev.submap_id == kf.submap_id:  # exact: no submap frames involved
                T = se3.inverse(prev.T_local_cam) @ kf.T_local_cam
            else:
                T = se3.project_rigid(se3.inverse(world_pose(gmap, prev)) @ world_pose(gmap, kf))
            if self.cfg.information == "fixed" or odometry_info is None:
                info = fixed_information(self.cfg.odometry_sigma_rot, self.cfg.odometry_sigma_trans)
            else:
                info = odometry_info
            self.odometry.append(Edge(prev.id, kf.id, T, info))

    # ---- detection and verification ------------------------------------------------------------------------

    def candidates(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap) -> list[LoopCandidate]:
        """Keyframes of earlier submaps at least Δ_min frames back: the top-k by descriptor cosine similarity above
        τ_sim, and (cfg.candidates 'pose' / 'both') the top-k by view overlap of the tracked poses (eq. 6's
        initial guess: distance, viewing angle, then reprojected depth)."""
        cfg = self.cfg
        T_q = world_pose(gmap, kf)
        pool = [o for o in keyframes if o.submap_id != kf.submap_id and kf.frame_index - o.frame_index >= cfg.min_index_gap
                and not (cfg.min_baseline > 0 and np.linalg.norm(world_pose(gmap, o)[:3, 3] - T_q[:3, 3]) < cfg.min_baseline)]
        out: list[LoopCandidate] = []
        if cfg.candidates in ("descriptor", "both"):
            scored = sorted(((float(np.dot(kf.descriptor, o.descriptor)), o) for o in pool if o.descriptor is not None),
                            key=lambda s: -s[0])
            for sim, other in scored[: cfg.top_k]:
                c = LoopCandidate(kf.id, other.id, kf.frame_index, other.frame_index, sim)
                if cfg.tau_sim is not None and sim < cfg.tau_sim:
                    c.reason = f"similarity {sim:.3f} < tau_sim {cfg.tau_sim}"
                    self.log.append(c)
                    continue
                out.append(c)
        if cfg.candidates in ("pose", "both"):
            taken = {c.match_kf for c in out}
            rest = [o for o in pool if o.id not in taken]
            near = nearest_by_overlap(kf.small, T_q, keyframe_poses(gmap, rest), [o.small for o in rest], rest, cfg)
            for ov, other in near[: cfg.pose_top_k]:
                sim = float(np.dot(kf.descriptor, other.descriptor)) if other.descriptor is not None else float("nan")
                c = LoopCandidate(kf.id, other.id, kf.frame_index, other.frame_index, sim, source="pose", overlap=ov)
                if ov < cfg.pose_min_overlap:
                    c.reason = f"overlap {ov:.2f} < pose_min_overlap {cfg.pose_min_overlap}"
                    self.log.append(c)
                    continue
                out.append(c)
        return out

    def verify(self, c: LoopCandidate, keyframes: list[Keyframe], gmap: GaussianMap) -> LoopCandidate:
        """Register query (source) to match (target) from the tracked guess (eq. 6), then apply the gates; a
        candidate that fails them takes the cloud route when the config allows (`detect` defers it instead)."""
        return self._verify_image(c, keyframes, gmap, cloud=True)[0]

    def _verify_image(self, c: LoopCandidate, keyframes: list[Keyframe], gmap: GaussianMap, *, cloud: bool
                      ) -> tuple[LoopCandidate, bool, np.ndarray]:
        """`verify` -> (the candidate, whether keyframe registration failed the fitness / RMSE gates, the tracked
        guess T_init); with `cloud` a gate failure goes on to the cloud route (budget permitting)."""
        cfg = self.cfg
        q, j = keyframes[c.query_kf], keyframes[c.match_kf]
        T_init = se3.project_rigid(se3.inverse(world_pose(gmap, j)) @ world_pose(gmap, q))  # eq. 6: T_j^-1 T_q
        if c.source == "descriptor" and not cfg.global_fallback and cfg.descriptor_min_overlap > 0:
            # Local registration cannot recover a pair the tracked poses do not make overlap: skip it cheaply.
            c.overlap = view_overlap(q.small, j.small, T_init)
            if c.overlap < cfg.descriptor_min_overlap:
                c.reason = f"overlap {c.overlap:.2f} < descriptor_min_overlap {cfg.descriptor_min_overlap} at the " \
                           f"tracked poses"
                self.log.append(c)
                return c, False, T_init
        r = register_loop(q.small, j.small, T_init, max_distance=cfg.icp_max_distance, min_fitness=cfg.fitness_min,
                          max_rmse=cfg.rmse_max, max_depth=self.max_depth, global_fallback=cfg.global_fallback)
        c.fitness, c.inlier_rmse = r.fitness, r.inlier_rmse
        c.correction_m = float(np.linalg.norm((se3.inverse(T_init) @ r.T_target_source)[:3, 3]))
        gates = r.fitness <= cfg.fitness_min or r.inlier_rmse >= cfg.rmse_max or not r.success
        if gates and cloud and cfg.cloud_route and self.cloud_tries.get(q.id, 0) < cfg.cloud_per_keyframe:
            return self._verify_cloud(c, q, j, keyframes, gmap, T_init), False, T_init
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
            self.loops.append(Edge(j.id, q.id, se3.project_rigid(r.T_target_source), self.loop_information(r), c))
        self.log.append(c)
        return c, gates, T_init

    def _verify_cloud(self, c: LoopCandidate, q: Keyframe, j: Keyframe, keyframes: list[Keyframe],
                      gmap: GaussianMap, T_init: np.ndarray, *, logged: bool = False) -> LoopCandidate:
        """The cloud route (slam.dense.loops.local_clouds): ICP between the two keyframes' windows from the tracked
        guess (the match window takes only keyframes older than the query window's, so the two share none), the
        cloud gates, the correction gate, then the render check of the match window's submaps from the result
        (without the submaps the query window was mapped into: the render must be independent evidence)."""
        from .local_clouds import WindowRegistrar, window_keyframes
        from .render_check import RenderGate, record_scores, score_loop

        cfg = self.cfg
        self.cloud_tries[q.id] = self.cloud_tries.get(q.id, 0) + 1
        if self.clouds is None:
            self.clouds = WindowRegistrar(radius=cfg.cloud_window, voxel=cfg.cloud_voxel,
                                          min_fitness=cfg.cloud_min_fitness, max_rmse=cfg.cloud_max_rmse)
        first = f"keyframe ICP fitness {c.fitness:.3f}, RMSE {c.inlier_rmse:.4f} m"
        c.route = "cloud"
        q_window = window_keyframes(keyframes, q, cfg.cloud_window)
        lo = min(k.id for k in q_window)
        wq = self.clouds.window(q.id, keyframes, gmap, q, max_depth=self.max_depth)
        wj = self.clouds.window(j.id, keyframes, gmap, j, max_depth=self.max_depth, below=lo)
        out = self.clouds.register(wq, wj, init=T_init)
        c.fitness, c.inlier_rmse = float(out.fitness), float(out.inlier_rmse)
        if out.T_match_query is None:
            c.reason = f"registration failed: {first}; cloud route: {out.reason}"
        elif out.reason:
            c.reason = f"{'inlier RMSE' if 'RMSE' in out.reason else 'fitness'}: cloud route: {out.reason} ({first})"
        else:
            T = se3.project_rigid(out.T_match_query)
            c.correction_m = float(np.linalg.norm((se3.inverse(T_init) @ T)[:3, 3]))
            s = score_loop(gmap, keyframes, j, T, q.small, cfg.cloud_window,
                           exclude_submaps={k.submap_id for k in q_window})
            record_scores(c, s)
            why = RenderGate(cfg.render_min_covisible, cfg.render_min_agree, cfg.render_max_violate,
                             cfg.render_max_photometric).verdict(s)
            if c.correction_m > cfg.max_correction:
                c.reason = f"correction {c.correction_m:.3f} m > max_correction {cfg.max_correction} (cloud route)"
            elif why:
                c.reason = f"render check: {why} (cloud route)"
            else:
                c.accepted, c.reason = True, "accepted [cloud route]"
                info = fixed_information(cfg.odometry_sigma_rot, cfg.odometry_sigma_trans)
                if cfg.information != "fixed":
                    cov = registration_covariance(out.information, out.n_correspondences, out.inlier_rmse, T,
                                                  self.model)
                    steps = step_covariances(self.odometry)
                    j_window = window_keyframes(keyframes, j, cfg.cloud_window, below=lo)
                    cov = cov + window_covariance(steps, q.id, [k.id for k in q_window]) + \
                        window_covariance(steps, j.id, [k.id for k in j_window])
                    info = information(cov, self.model)
                self.loops.append(Edge(j.id, q.id, T, info, c))
        if not logged:
            self.log.append(c)
        return c

    def loop_information(self, r) -> np.ndarray:
        """Information of an accepted registration (slam.dense.loops.edge_information), or the fixed sigmas."""
        if self.cfg.information == "fixed":
            return fixed_information(self.cfg.odometry_sigma_rot, self.cfg.odometry_sigma_trans)
        cov = registration_covariance(r.information, r.n_correspondences, r.inlier_rmse, r.T_target_source, self.model)
        return information(cov, self.model)

    def detect(self, kf: Keyframe, keyframes: list[Keyframe], gmap: GaussianMap) -> list[LoopCandidate]:
        """Candidates for `kf`, each verified; returns the accepted ones. The cloud route is the keyframe's
        fallback: only when keyframe registration accepted none of its candidates do those that failed its gates
        take the route (best first, at most cloud_per_keyframe) — where images already close the revisit, the
        coarser cloud loops would only add time and millimetres."""
        done = [self._verify_image(c, keyframes, gmap, cloud=False) for c in self.candidates(kf, keyframes, gmap)]
        if self.cfg.cloud_route and not any(c.accepted for c, _, _ in done):
            for c, gates, T_init in done:
                if gates and self.cloud_tries.get(kf.id, 0) < self.cfg.cloud_per_keyframe:
                    q, j = keyframes[c.query_kf], keyframes[c.match_kf]
                    self._verify_cloud(c, q, j, keyframes, gmap, T_init, logged=True)
        return [c for c, _, _ in done if c.accepted]

    # ---- optimisation ------------------------------------------------------------------------------------

    def reject(self, e: Edge, reason: str) -> None:
        e.rejected = True
        if e.candidate is not None:
            e.candidate.accepted, e.candidate.reason = False, reason

    def optimise(self, keyframes: list[Keyframe], gmap: GaussianMap) -> dict:
        """Pose-graph optimisation over keyframe poses; loops the optimum cannot satisfy are rejected and the graph
        solved again (slam.dense.loops.loop_check); an optimum that moves keyframes further than the loops justify is not
        applied (its new loops are rejected). Otherwise every submap moves rigidly to the optimised pose of its
        first keyframe (eqs. 14–15; keyframes and Gaussians follow their submap)."""
        cfg = self.cfg
        initial = {kf.id: world_pose(gmap, kf) for kf in keyframes}
        fixed = keyframes[0].id
        new = [e for e in self.loops if not e.rejected and not e.applied]
        optimised, rejected = initial, 0
        while self.active_loops:
            loops = self.active_loops
            optimised = self._solve(initial, loops, fixed)
            bad = loop_check.worst_violation(optimised, [(e.i, e.j, e.T_ij) for e in loops],
                                             cfg.residual_max_trans, cfg.residual_max_deg)
            if bad is None:
                break
            self.reject(loops[bad.index], f"inconsistent after optimisation: residual {100 * bad.trans_m:.1f} cm / "
                                          f"{bad.rot_deg:.2f} deg > {100 * cfg.residual_max_trans:.1f} cm / "
                                          f"{cfg.residual_max_deg} deg")
            rejected += 1
        else:  # every loop was rejected: nothing to move
            optimised = initial
        self.optimisations += 1
        moved = loop_check.max_move(initial, optimised)
        allowed = loop_check.justified_move(initial, [(e.i, e.j, e.T_ij) for e in self.active_loops],
                                            cfg.max_move_factor, cfg.max_move_slack)
        if moved > allowed:
            self.not_applied += 1
            for e in new:
                if not e.rejected:
                    self.reject(e, f"optimisation would move keyframes {moved:.3f} m, more than the loops justify "
                                   f"({allowed:.3f} m): not applied")
            warnings.warn(f"loop closure: optimisation not applied (it would move keyframes {moved:.3f} m, the loops "
                          f"justify {allowed:.3f} m)", RuntimeWarning, stacklevel=2)
            return {"submaps_moved": 0, "max_shift_m": 0.0, "rejected": rejected, "applied": False}
        for e in self.loops:
            e.applied = True
        self.optimum = {k: np.array(T) for k, T in optimised.items()}
        shifts = []
        for s in gmap.submaps:
            if not s.keyframe_ids:
                continue
            first = keyframes[s.keyframe_ids[0]]
            D = gmap.place_submap(s, optimised[first.id] @ se3.inverse(first.T_local_cam))
            shifts.append(float(np.linalg.norm(D[:3, 3])))
        return {"submaps_moved": len(shifts), "max_shift_m": max(shifts, default=0.0), "rejected": rejected,
                "applied": True}

    def _solve(self, initial: dict[int, np.ndarray], loops: list[Edge], fixed: int) -> dict[int, np.ndarray]:
        """The pose graph's optimum: incrementally (slam.dense.loops.incremental, config solver 'incremental')
        or re-solved whole ('batch'); the incremental graph falls back to a batch solve, and starts anew, when
        iSAM2 fails."""
        if self.cfg.solver == "incremental":
            graph = getattr(self, "_graph", None)
            if graph is None:
                graph = self._graph = IncrementalGraph()
            try:
                return graph.solve(initial, self.odometry, self.loops, fixed)
            except RuntimeError as err:  # e.g. an indeterminate system: iSAM2's state is not to be trusted
                warnings.warn(f"incremental pose-graph optimisation failed ({err}); solved whole instead",
                              stacklevel=2)
                self._graph = None
        return optimise_pose_graph(initial, self.odometry, loops, fixed=fixed)

    def cloud_stats(self) -> dict:
        """The cloud route's work and outcome: windows built, registrations and their seconds, candidates that
        took it, accepted, and rejected by the render check."""
        from .local_clouds import WindowRegistrar

        st = (self.clouds or WindowRegistrar()).stats()
        rs = [c for c in self.log if c.route == "cloud"]
        return {"enabled": self.cfg.cloud_route, **st, "query_keyframes": len(self.cloud_tries),
                "candidates": len(rs), "accepted": sum(c.accepted for c in rs),
                "rejected_render": sum(c.reason.startswith("render") for c in rs)}

    def log_rows(self) -> list[dict]:
        return [asdict(c) for c in self.log]


def optimise_pose_graph(initial: dict[int, np.ndarray], odometry: list[Edge], loops: list[Edge], *,
                        fixed: int) -> dict[int, np.ndarray]:
    """Levenberg–Marquardt over keyframe poses (eq. 13) with `graph/`: tracking and loop edges as relative-pose
    constraints with their information (twist order [omega, v]); the graph anchors its first pose (the first
    keyframe, `fixed`)."""
    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.pose_graph import PoseGraph
    from swarmsplat.graph.solvers import solve

    from swarmsplat.kernels.errors import SwarmsplatError

    g = PoseGraph()
    for k in sorted(initial):
        g.add_pose(k, initial[k])

    for e in odometry:
        g.add_odometry(e.i, e.j, e.T_ij, e.info)
    for e in loops:
        g.add_loop(e.i, e.j, e.T_ij, e.info)
    try:
        res = solve(build_problem(g, "base"), "lm")
    except (SwarmsplatError, RuntimeError) as err:  # an indeterminate system: keep the tracked poses
        warnings.warn(f"pose-graph optimisation failed ({err}); poses left as tracked", stacklevel=2)
        return dict(initial)
    out = {k: se3.project_rigid(res.poses[k]) for k in initial}
    # The graph anchors each component at its own choice of pose; re-anchor at `fixed` so that frame stays put.
    D = initial[fixed] @ se3.inverse(out[fixed])
    return {k: se3.project_rigid(D @ T) for k, T in out.items()}
