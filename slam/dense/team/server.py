"""GRAND-SLAM's server side (§III-D–E): it receives every agent's keyframes (descriptor, small RGB-D copy, pose)
and reads their submaps, finds intra- and inter-agent loop closures, keeps one multi-agent pose graph over all
keyframe poses, and moves submaps to the optimised poses (eqs. 14–15).

Frames. Each agent tracks in its own world frame (its first camera). The server keeps, per agent,
`T_global_world`: where that frame sits in its *component's* frame. A component is a set of agents linked by
accepted inter-agent loops; its frame is that of its lowest-numbered agent. Agents start alone (identity); an
agent joins another's frame on two mutually consistent inter-agent loops (slam.dense.team.joins). Agents whose
views never overlap are never linked, and each keeps its own frame (the pose graph anchors one key per
connected component, `graph.PoseGraph.anchors`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
import numpy as np
from swarmsplat.kernels import se3

from swarmsplat.slam.dense.agent import Agent
from swarmsplat.slam.dense.gaussian_map import GaussianParams, transform_params
from swarmsplat.slam.dense.loops import loop_check
from swarmsplat.slam.dense.loops.edge_information import fixed_information
from swarmsplat.slam.dense.loops.loop_log import INTER, LoopRecord, from_intra
from swarmsplat.slam.config import ServerConfig  # noqa: F401  (re-exported: slam.dense.team.server.ServerConfig)
from swarmsplat.slam.dense.team.descriptors import coarse_view, describe_keyframe, make_recognizer_and_encoder
from swarmsplat.slam.dense.team.cloud_route import CloudRoute, gate_failure
from swarmsplat.slam.dense.team.joins import JoinRules
from swarmsplat.slam.dense.team.team_graph import TeamGraph
from swarmsplat.slam.dense.submaps import Keyframe, follow_keyframe_optimum, world_pose


_rigid = se3.project_rigid  # poses composed from many tracked and moved frames drift off SE(3)


@dataclass
class InterLoop:
    agent_i: int  # match (target) agent and keyframe
    kf_i: int
    agent_j: int  # query (source) agent and keyframe
    kf_j: int
    T_ij: np.ndarray  # [4, 4] pose of keyframe j's camera in keyframe i's camera
    record: LoopRecord
    info: np.ndarray | None = None  # [6, 6] from the registration (None: the server's fixed loop sigmas)
    rejected: bool = False
    applied: bool = False


@dataclass
class AgentSlot:
    """What the server knows about one agent."""

    agent: Agent
    robot: str  # one-character pose-graph robot id
    T_global_world: np.ndarray = field(default_factory=lambda: np.eye(4))  # [4, 4] agent world -> component frame
    component: int = 0  # index of the lowest agent of its component
    intra_logged: int = 0  # how many of agent.loops.log are already in the server's records
    intra_accepted: list = field(default_factory=list)  # records of agent.loops.loops, edge n <-> record n


class Server(JoinRules, CloudRoute, TeamGraph):
    def __init__(self, agents: list[Agent], config: ServerConfig | None = None):
        self.cfg = config or ServerConfig()
        self.slots = [AgentSlot(a, chr(ord("a") + i), component=i) for i, a in enumerate(agents)]
        self.inter: list[InterLoop] = []
        self.records: list[LoopRecord] = []
        self.rejected_edges: set[tuple] = set()  # GNC outliers, left out of later graphs
        self.optimisations = 0
        self.not_applied = 0  # optimisations whose move the loops did not justify
        self.time = {"intra": 0.0, "inter": 0.0, "optimisation": 0.0}
        self.last_graph = None  # (PoseGraph, optimised poses) of the last optimisation
        self.descriptors: dict[tuple[int, int], np.ndarray] = {}  # (agent, keyframe id) -> unit vector
        self.inter_stats: dict = {}  # per source and coarse method: candidates, accepted, seconds
        self.pending: list[InterLoop] = []  # verified loops between components waiting for a consistent second
        self.joins = 0
        self.joins_undone = 0
        self._untrained: list[tuple[int, int]] = []  # xfeat-vlad keyframes waiting for the vocabulary
        # The server's place recognizer (None: the agents' own descriptors) and its XFeat keyframe encoder.
        self.recognizer, self.encoder = make_recognizer_and_encoder(self.cfg)
        # The cloud route's cached keyframe windows and how often it ran per query keyframe (slam.dense.team.cloud_route).
        self.clouds = None  # made on first use, from the agents' loop_closure section
        self.cloud_tries: dict[tuple[int, int], int] = {}

    # ---- the server loop: one call per keyframe an agent sends --------------------------------------------------

    def on_keyframe(self, a: int, kf: Keyframe, step: int = 0) -> list[LoopRecord]:
        """Look for loops of agent `a`'s new keyframe (its own, then the other agents'); optimise and move submaps
        when one is accepted. Returns the new candidate records."""
        t0 = time.perf_counter()
        self._describe(a, kf)
        new = self._intra(a, kf, step) if self.cfg.intra_loops else []
        t1 = time.perf_counter()
        if self.cfg.inter_loops:
            new += [self.verify_inter(a, kf, b, m, sim, step) for b, m, sim in self.inter_candidates(a, kf, step)]
            new += [self.verify_inter(a, kf, b, m, sim, step, source="pose")
                    for b, m, sim in self.inter_pose_candidates(a, kf, step)]
        t2 = time.perf_counter()
        self.time["intra"] += t1 - t0
        self.time["inter"] += t2 - t1
        if any(r.accepted for r in new):
            self._unsolved = True
        if self.__dict__.get("_unsolved") and self._solve_due():
            self.optimise()
        return new

    def keyframe_count(self) -> int:
        return sum(len(s.agent.keyframes) for s in self.slots)

    def _solve_due(self) -> bool:
        """Whether accepted loops waiting for a solve are solved now (config server.optimise_fraction): always when
        the fraction is 0 or two components joined since the last solve; otherwise once that fraction of the team's
        keyframes has arrived since it, so a mission of N keyframes is solved O(log N / fraction) times, not at
        nearly every keyframe (the team's last solve, Team.finish and the process server's end, takes the rest)."""
        f = self.cfg.optimise_fraction
        last = self.__dict__.get("_solved_at", (0, 0))  # (keyframes, joins) at the last solve
        n = self.keyframe_count()
        return f <= 0 or self.joins != last[1] or n - last[0] >= f * n

    def _describe(self, a: int, kf: Keyframe) -> None:
        """The server's descriptor of agent a's keyframe into self.descriptors (slam.dense.team.descriptors)."""
        describe_keyframe(self, a, kf)

    def _intra(self, a: int, kf: Keyframe, step: int) -> list[LoopRecord]:
        slot = self.slots[a]
        ag = slot.agent
        ag.loops.detect(kf, ag.keyframes, ag.gmap)
        new = [from_intra(ag.name, c, step) for c in ag.loops.log[slot.intra_logged:]]
        slot.intra_logged = len(ag.loops.log)
        slot.intra_accepted += [r for r in new if r.accepted]
        self.records += new
        return new

    # ---- inter-agent candidates and their verification ---------------------------------------------------------

    def inter_candidates(self, a: int, kf: Keyframe, step: int = 0) -> list[tuple[int, Keyframe, float]]:
        """The `top_k` most similar keyframes of the other agents (similarity ≥ τ_sim when a gate is set; by
        default none: verification decides). With a gate, the best one below it is logged (reason `similarity`),
        so a pair of agents that never matches is visible in loops.csv."""
        d = self.descriptors.get((a, kf.id))
        if d is None:
            return []
        scored = []
        for b, slot in enumerate(self.slots):
            if b == a:
                continue
            for m in slot.agent.keyframes:
                e = self.descriptors.get((b, m.id))
                if e is not None:
                    scored.append((float(np.dot(d, e)), b, m))
        scored.sort(key=lambda s: -s[0])
        tau = self.cfg.tau_sim
        out = [(b, m, s) for s, b, m in scored[: self.cfg.top_k] if tau is None or s >= tau]
        if not out and scored:
            s, b, m = scored[0]
            self.records.append(self._record(a, kf, b, m, s, step).reject(
                "similarity", f"similarity {s:.3f} < tau_sim {tau}"))
        return out

    def inter_pose_candidates(self, a: int, kf: Keyframe, step: int = 0) -> list[tuple[int, Keyframe, float]]:
        """Once agents share a frame, their poses propose candidates too (as intra-agent ones, eq. 6): keyframes
        of the other agents of a's component near kf's pose, by view overlap; loop_closure.pose_top_k of them,
        skipping those the descriptor already proposed."""
        from swarmsplat.slam.dense.loops.view_overlap import keyframe_poses, nearest_by_overlap

        lc = self.slots[a].agent.cfg.loop_closure
        if lc.candidates == "descriptor" or lc.pose_top_k == 0:
            return []
        T_q = self.global_pose(a, kf)
        taken = {(r.match_agent, r.match_kf) for r in self.records[-2 * self.cfg.top_k:]
                 if r.kind == INTER and r.query_agent == self.slots[a].agent.name and r.query_kf == kf.id}
        poses, smalls, payloads = [], [], []
        for b, slot in enumerate(self.slots):
            if b == a or slot.component != self.slots[a].component:
                continue
            rest = [m for m in slot.agent.keyframes if (slot.agent.name, m.id) not in taken]
            poses.append(slot.T_global_world @ keyframe_poses(slot.agent.gmap, rest))
            smalls += [m.small for m in rest]
            payloads += [(b, m) for m in rest]
        poses = np.concatenate(poses) if poses else np.zeros((0, 4, 4))
        out = []
        for ov, (b, m) in nearest_by_overlap(kf.small, T_q, poses, smalls, payloads, lc)[: lc.pose_top_k]:
            d, e = self.descriptors.get((a, kf.id)), self.descriptors.get((b, m.id))
            sim = float(np.dot(d, e)) if d is not None and e is not None else float("nan")
            if ov < lc.pose_min_overlap:
                rec = self._record(a, kf, b, m, sim, step)
                rec.source = "pose"
                self.records.append(rec.reject("overlap", f"overlap {ov:.2f} < pose_min_overlap {lc.pose_min_overlap}"))
                continue
            out.append((b, m, sim))
        return out

    def _record(self, a: int, q: Keyframe, b: int, m: Keyframe, sim: float, step: int) -> LoopRecord:
        return LoopRecord(INTER, self.slots[a].agent.name, q.id, q.frame_index, self.slots[b].agent.name, m.id,
                          m.frame_index, float(sim), step=step)

    def verify_inter(self, a: int, q: Keyframe, b: int, m: Keyframe, sim: float, step: int = 0, *,
                     source: str = "descriptor") -> LoopRecord:
        """Register agent a's keyframe q (source) to agent b's keyframe m (target): coarse RGB-D, then ICP, then
        the fitness / RMSE gates. Agents already in one frame start from their current relative pose (eq. 6) and
        must also pass the correction gate; agents in different frames start from the learned guess (server.coarse
        'learned': cached XFeat encodings matched, lifted with depth; not found -> a rejected candidate, reason
        code `registration`) or from identity with the FPFH + RANSAC fallback ('fpfh'). Seconds and counts per
        source / coarse method go to `inter_stats`. An accepted loop either links two components (the join) or is a pose-graph edge."""
        from swarmsplat.registration.rgbd import register_rgbd

        lc = self.slots[a].agent.cfg.loop_closure
        rec = self._record(a, q, b, m, sim, step)
        rec.source = source
        self.records.append(rec)
        same = self.slots[a].component == self.slots[b].component
        t0 = time.perf_counter()
        method = "pose" if same else self.cfg.coarse
        try:
            return self._verify(rec, a, q, b, m, same, lc, register_rgbd)
        finally:
            key = f"{source}/{'cloud' if rec.route == 'cloud' else method}"
            st = self.inter_stats.setdefault(key, {"candidates": 0, "accepted": 0, "seconds": 0.0})
            st["candidates"] += 1
            st["accepted"] += int(rec.accepted)
            st["seconds"] += time.perf_counter() - t0

    def _verify(self, rec, a, q, b, m, same, lc, register_rgbd) -> LoopRecord:
        T_init = _rigid(se3.inverse(self.global_pose(b, m)) @ self.global_pose(a, q)) if same else np.eye(4)
        if q.small.camera.K.tolist() != m.small.camera.K.tolist() or q.small.color.shape != m.small.color.shape:
            if not same and self.cloud_allowed(a, q):  # clouds are metric: the cameras need not be alike
                return self.verify_cloud(rec, a, q, b, m, "the two keyframes have different cameras")
            rec.registration = "camera models differ"
            return rec.reject("registration", "registration failed: the two keyframes have different cameras")
        depth_max = self.slots[a].agent.cfg.image.max_depth
        fallback = self.cfg.global_fallback and (self.cfg.same_frame_fallback if same else True)
        if not same and self.cfg.coarse == "learned":
            T_guess, info = self.encoder.guess((a, q.id), coarse_view(q), (b, m.id), coarse_view(m))
            fallback = self.cfg.global_fallback and self.cfg.learned_fallback
            if T_guess is not None:
                T_init = T_guess
            elif not fallback:
                if self.cloud_allowed(a, q):
                    return self.verify_cloud(rec, a, q, b, m, f"learned coarse guess not found ({info['reason']})")
                rec.registration = f"learned guess: {info['reason']}"
                return rec.reject("registration", f"registration failed: learned coarse guess not found "
                                                  f"({info['reason']})")
        r = register_rgbd(q.small.color, q.small.depth, m.small.color, m.small.depth, q.small.camera, T_init,
                          max_distance=lc.icp_max_distance, min_fitness=lc.fitness_min, max_rmse=lc.rmse_max,
                          global_fallback=fallback, depth_max=depth_max)
        rec.registration, rec.fitness, rec.inlier_rmse = r.reason, float(r.fitness), float(r.inlier_rmse)
        failed = gate_failure(r, lc)
        if failed and self.cloud_allowed(a, q, same):  # one frame: the windows' ICP from the same start
            return self.verify_cloud(rec, a, q, b, m, f"keyframe ICP: {failed[1]}", init=T_init if same else None)
        if failed:
            return rec.reject(*failed)
        ag = self.slots[a].agent
        info = ag.loops.loop_information(r) if ag.cfg.loop_closure.information == "registration" else None
        loop = InterLoop(b, m.id, a, q.id, _rigid(r.T_target_source), rec, info)
        if not same:
            if self.cfg.render_check == "all":
                why = self.render_score(b, m, loop.T_ij, q, rec)
                if why:
                    return rec.reject("render", why)
            return self._join_or_wait(loop, r.method)
        rec.correction_m = float(np.linalg.norm((se3.inverse(T_init) @ r.T_target_source)[:3, 3]))
        if rec.correction_m > lc.max_correction:
            return rec.reject("correction", f"correction {rec.correction_m:.3f} m > max_correction {lc.max_correction}")
        rec.accepted, rec.reason_code, rec.reason = True, "accepted", f"accepted [{r.method}]"
        self.inter.append(loop)
        return rec

    # ---- poses, the pose graph and the submap moves -------------------------------------------------------------

    def global_pose(self, a: int, kf: Keyframe) -> np.ndarray:
        """T [4, 4] of a keyframe camera in its component's frame."""
        s = self.slots[a]
        return s.T_global_world @ world_pose(s.agent.gmap, kf)

    def key(self, a: int, kf_id: int) -> int:
        from swarmsplat.graph.pose_graph import robot_key

        return robot_key(self.slots[a].robot, kf_id)

    def optimise(self) -> dict:
        """LM (or GNC) over the whole team's keyframe poses; loops the optimum cannot satisfy are rejected and the
        graph solved again, and an optimum that moves keyframes further than the loops justify is not applied
        (slam.dense.loops.loop_check, the agents' loop_closure limits). Otherwise every submap moves to the optimised pose of
        its first keyframe (eq. 14), expressed back in its agent's own world frame."""
        from swarmsplat.graph.formulations import build_problem
        from swarmsplat.graph.solvers import solve

        t0 = time.perf_counter()
        self._unsolved, self._solved_at = False, (self.keyframe_count(), self.joins)
        lc = self.slots[0].agent.cfg.loop_closure
        new = self._unapplied_loops()
        rejected = 0
        while True:
            g, tags = self.build_graph()
            res = solve(build_problem(g, "base"), self.cfg.solver)
            if res.rejected:
                self._mark_gnc(g, tags, res.rejected)
            loop_edges = [(n, e) for n, e in enumerate(g.edges) if tags[n] is not None]
            bad = loop_check.worst_violation(res.poses, [(e.key_i, e.key_j, e.T_ij) for _, e in loop_edges],
                                             lc.residual_max_trans, lc.residual_max_deg)
            if bad is None:
                break
            self._reject_edge(tags[loop_edges[bad.index][0]], "inconsistent",
                              f"inconsistent after optimisation: residual {100 * bad.trans_m:.1f} cm / "
                              f"{bad.rot_deg:.2f} deg > {100 * lc.residual_max_trans:.1f} cm / {lc.residual_max_deg} deg")
            rejected += 1
        self.optimisations += 1
        moved = loop_check.max_move(g.poses, res.poses)
        allowed = loop_check.justified_move(g.poses, [(e.key_i, e.key_j, e.T_ij) for e in g.edges if e.kind == "loop"],
                                            lc.max_move_factor, lc.max_move_slack)
        if moved > allowed:
            self.not_applied += 1
            for tag in new:
                self._reject_edge(tag, "move", f"optimisation would move keyframes {moved:.3f} m, more than the "
                                               f"loops justify ({allowed:.3f} m): not applied")
            self.time["optimisation"] += time.perf_counter() - t0
            return {"submaps_moved": 0, "max_shift_m": 0.0, "solver": res.solver, "rejected": rejected,
                    "applied": False, "joins_undone": self._split_unsupported()}
        self._mark_applied()
        shifts = []
        for a, s in enumerate(self.slots):
            kfs = s.agent.keyframes
            W_from_G = se3.inverse(s.T_global_world)
            for sm in s.agent.gmap.submaps:
                if not sm.keyframe_ids:
                    continue
                first = kfs[sm.keyframe_ids[0]]
                D = s.agent.gmap.place_submap(sm, W_from_G @ res.poses[self.key(a, first.id)]
                                              @ se3.inverse(first.T_local_cam))
                shifts.append(float(np.linalg.norm(D[:3, 3])))
        self.last_graph = (g, res.poses)
        self.time["optimisation"] += time.perf_counter() - t0
        return {"submaps_moved": len(shifts), "max_shift_m": max(shifts, default=0.0), "solver": res.solver,
                "rejected": rejected + len(res.rejected), "applied": True, "joins_undone": self._split_unsupported()}

    def _unapplied_loops(self) -> list[tuple]:
        out = [("intra", a, n) for a, s in enumerate(self.slots) for n, e in enumerate(s.agent.loops.loops)
               if not e.rejected and not e.applied]
        return out + [("inter", n) for n, L in enumerate(self.inter) if not L.rejected and not L.applied]

    def _mark_applied(self) -> None:
        for s in self.slots:
            for e in s.agent.loops.loops:
                e.applied = True
        for L in self.inter:
            L.applied = True

    def _reject_edge(self, tag: tuple, code: str, reason: str) -> None:
        """Leave a loop out of later graphs and say why in its record."""
        if tag[0] == "inter":
            L = self.inter[tag[1]]
            L.rejected = True
            L.record.reject(code, reason)
            return
        _, a, n = tag
        slot = self.slots[a]
        slot.agent.loops.reject(slot.agent.loops.loops[n], reason)
        if n < len(slot.intra_accepted):
            slot.intra_accepted[n].reject(code, reason)

    def _mark_gnc(self, g, tags, rejected: list[int]) -> None:
        for e in rejected:
            tag = tags[e]
            if tag is None:
                continue
            self.rejected_edges.add(tag)
            if tag[0] == "inter":
                rec = self.inter[tag[1]].record
            else:
                acc = self.slots[tag[1]].intra_accepted
                rec = acc[tag[2]] if tag[2] < len(acc) else None
            if rec is not None:
                rec.reject("gnc", "rejected by GNC as inconsistent with the other loops and odometry")

    # ---- results ---------------------------------------------------------------------------------------------

    def components(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for a, s in enumerate(self.slots):
            out.setdefault(s.component, []).append(a)
        return out

    def global_trajectory(self, a: int, *, per_keyframe: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps [N], T [N, 4, 4]) of agent a's frames in its component's frame.

        per_keyframe=False: every frame moves rigidly with its submap (eq. 14), consistent with the map (for
        rendering). per_keyframe=True: every frame follows the pose-graph optimum of the last keyframe before it in
        its submap (T = T_kf^g · T_kf_local⁻¹ · T_frame_local) — the best trajectory estimate the graph gives, since a
        submap's later keyframes have their own optimised poses that the rigid submap move ignores. Frames whose
        keyframe is not in the last optimised graph keep the rigid move. Once the map refinement has refined a
        keyframe's pose (Keyframe.T_local_refined), its frames follow that pose in both modes: it is the pose the
        map was fitted to, refined from the pose-graph optimum."""
        s = self.slots[a]
        stamps, T = s.agent.trajectory()
        if not len(T):
            return stamps, T
        T = s.T_global_world[None] @ T
        if per_keyframe and self.last_graph is not None:
            optimum = self.last_graph[1]
            follow_keyframe_optimum(T, s.agent.poses, s.agent.keyframes, lambda kf: optimum.get(self.key(a, kf.id)))
        return stamps, T

    def refine_maps(self, cfg, mapping, exposure=None) -> dict:
        """Global map refinement of every component after the final optimisation (slam.dense.mapping.refine);
        `exposure` (ExposureConfig) refines the keyframes' exposures with the maps."""
        from swarmsplat.slam.dense.mapping.refine import refine_components

        t0 = time.perf_counter()
        out = refine_components(self, cfg, mapping, exposure)
        self.time["refine"] = self.time.get("refine", 0.0) + time.perf_counter() - t0
        return out

    def display_map(self, component: int = 0) -> GaussianParams:
        """merged_map(component) with its colours as a typical keyframe of its agents saw them (what map.ply holds:
        slam.dense.mapping.exposure.for_display)."""
        from swarmsplat.slam.dense.mapping.exposure import for_display

        return for_display(self.merged_map(component), self.keyframes_of(component))

    def keyframes_of(self, component: int = 0) -> list:
        """Every keyframe of the agents in `component` (their exposures give its map's display colours)."""
        return [kf for s in self.slots if s.component == component for kf in s.agent.keyframes]

    def merged_map(self, component: int = 0) -> GaussianParams:
        """All Gaussians of the agents in `component`, in that component's frame (eq. 15 per submap)."""
        parts = []
        for s in self.slots:
            if s.component != component:
                continue
            for sm in s.agent.gmap.submaps:
                if len(sm):
                    parts.append(transform_params(sm.params, s.T_global_world @ sm.T_world_local))
        return GaussianParams.concat(parts)
