"""The team server's 3-D route for agents not yet in one frame (slam.dense.team.server.Server): when two keyframes
share too few image features for a start (wide baselines, opposite viewpoints), their local maps — a window of
keyframes each, fused with depth — are registered as point clouds without a guess (slam.dense.loops.local_clouds),
and the pose is checked by rendering the matched agent's Gaussian submaps from the query keyframe's hypothesised
pose (slam.dense.loops.render_check). A loop that passes goes to the join rules like any other.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3

from swarmsplat.slam.dense.loops.loop_log import LoopRecord
from swarmsplat.slam.dense.loops.render_check import RenderGate, record_scores, score_loop
from swarmsplat.slam.dense.submaps import Keyframe


def make_window_registrar(lc, method: str = "auto"):
    """The WindowRegistrar of loop_closure section `lc` (window, voxel, gates) with global registration `method`."""
    from swarmsplat.slam.dense.loops.local_clouds import WindowRegistrar

    return WindowRegistrar(radius=lc.cloud_window, voxel=lc.cloud_voxel, method=method,
                           min_fitness=lc.cloud_min_fitness, max_rmse=lc.cloud_max_rmse)


def gate_failure(r, lc) -> tuple[str, str] | None:
    """(reason code, sentence) of a keyframe registration `r` that fails loop_closure `lc`'s gates, else None."""
    if not r.success and r.reason != "poor alignment":
        return "registration", f"registration failed: {r.reason}"
    if r.fitness <= lc.fitness_min:
        return "fitness", f"fitness {r.fitness:.3f} <= tau_f {lc.fitness_min}"
    if r.inlier_rmse >= lc.rmse_max:
        return "rmse", f"inlier RMSE {r.inlier_rmse:.4f} m >= tau_rho {lc.rmse_max}"
    if not r.success:
        return "registration", f"registration failed: {r.reason}"
    return None


def render_gate(lc, join_max_violate: float | None = None) -> RenderGate:
    """The render check's gate from loop_closure section `lc`; a loop that would join two frames takes the
    stricter free-space share `join_max_violate` (server.join_max_violate) when given."""
    violate = lc.render_max_violate if join_max_violate is None else min(lc.render_max_violate, join_max_violate)
    return RenderGate(lc.render_min_covisible, lc.render_min_agree, violate, lc.render_max_photometric)


class CloudRoute:
    """Mixed into the Server (reads its slots, cfg, clouds, cloud_tries, join rules)."""

    def cloud_allowed(self, a: int, q: Keyframe, same: bool = False) -> bool:
        """Whether the cloud route may still run for agent a's keyframe q (loop_closure.cloud_per_keyframe):
        between agents in two frames under server.cloud_route, between agents already in one frame (ICP from their
        current relative pose, as within one agent) under loop_closure.cloud_route, and then only while no loop of
        q has been accepted."""
        lc = self.slots[a].agent.cfg.loop_closure
        on = lc.cloud_route if same else self.cfg.cloud_route
        if same and on and self.closed_already(a, q):  # a fallback, as within one agent (LoopCloser.detect)
            return False
        return on and self.cloud_tries.get((a, q.id), 0) < lc.cloud_per_keyframe

    def closed_already(self, a: int, q: Keyframe) -> bool:
        """Whether a loop of agent a's keyframe q was accepted while it was being checked (its records are the
        newest): then the cloud route between agents in one frame adds nothing the images did not."""
        name = self.slots[a].agent.name
        for r in reversed(self.records):
            if r.query_agent != name or r.query_kf != q.id:
                return False
            if r.accepted:
                return True
        return False

    def render_score(self, b: int, m: Keyframe, T_m_q: np.ndarray, q: Keyframe, rec: LoopRecord, *,
                     join: bool = True) -> str:
        """Render agent b's submaps around keyframe m from q's hypothesised pose (m's camera @ T_m_q), score
        against q's loop-closure copy, record the scores on `rec`; '' when the gate passes, else the reason.
        `join`: the loop would join two frames (server.join_max_violate applies)."""
        ag = self.slots[b].agent
        lc = ag.cfg.loop_closure
        s = score_loop(ag.gmap, ag.keyframes, m, T_m_q, q.small, lc.cloud_window)
        record_scores(rec, s)
        return render_gate(lc, self.cfg.join_max_violate if join else None).verdict(s)

    def _cloud_information(self, out, T: np.ndarray, a: int, q: Keyframe, b: int, m: Keyframe) -> np.ndarray:
        """A cloud loop's information: the registration's covariance plus both windows' tracking spread
        (slam.dense.loops.edge_information.window_covariance), as within one agent."""
        from swarmsplat.slam.dense.loops.edge_information import (information, registration_covariance,
                                                                step_covariances, window_covariance)
        from swarmsplat.slam.dense.loops.local_clouds import window_keyframes

        sa, sb = self.slots[a].agent, self.slots[b].agent
        model, r = sa.loops.model, sa.cfg.loop_closure.cloud_window
        cov = registration_covariance(out.information, out.n_correspondences, out.inlier_rmse, T, model)
        for ag, kf in ((sa, q), (sb, m)):
            members = [k.id for k in window_keyframes(ag.keyframes, kf, r)]
            cov = cov + window_covariance(step_covariances(ag.loops.odometry), kf.id, members)
        return information(cov, model)

    def verify_cloud(self, rec: LoopRecord, a: int, q: Keyframe, b: int, m: Keyframe, image_reason: str,
                     init: np.ndarray | None = None):
        """The cloud route for the candidate (q of agent a, m of agent b): register the two windows (by global
        registration, or by ICP from `init` = T_m_q when the agents are already in one frame), gate by the clouds'
        fitness and RMSE and by rendering, then hand the loop to the join rules (agents in two frames) or keep it
        as a loop after the correction gate (one frame). `image_reason`: why the image route gave nothing, kept in
        the reason of a rejection."""
        from .server import InterLoop

        self.cloud_tries[(a, q.id)] = self.cloud_tries.get((a, q.id), 0) + 1
        rec.route = "cloud"
        sa, sb = self.slots[a].agent, self.slots[b].agent
        if self.clouds is None:
            self.clouds = make_window_registrar(sa.cfg.loop_closure, self.cfg.cloud_method)
        wq = self.clouds.window((a, q.id), sa.keyframes, sa.gmap, q, max_depth=sa.cfg.image.max_depth)
        wm = self.clouds.window((b, m.id), sb.keyframes, sb.gmap, m, max_depth=sb.cfg.image.max_depth)
        out = self.clouds.register(wq, wm, init=init)
        rec.registration = f"cloud/{out.method}: {out.reason or 'ok'}"
        rec.fitness, rec.inlier_rmse = float(out.fitness), float(out.inlier_rmse)
        if out.T_match_query is None:
            return rec.reject("registration", f"registration failed: image route: {image_reason}; cloud route: "
                                              f"{out.reason}")
        if out.reason:
            code = "rmse" if "RMSE" in out.reason else "fitness"
            return rec.reject(code, f"cloud route: {out.reason} (image route: {image_reason})")
        T = se3.project_rigid(out.T_match_query)
        why = self.render_score(b, m, T, q, rec, join=init is None)
        if why:
            return rec.reject("render", f"cloud route: {why}")
        info = None
        if sa.cfg.loop_closure.information == "registration":
            info = self._cloud_information(out, T, a, q, b, m)
        loop = InterLoop(b, m.id, a, q.id, T, rec, info)
        if init is None:
            return self._join_or_wait(loop, f"cloud/{out.method}")
        rec.correction_m = float(np.linalg.norm((se3.inverse(init) @ T)[:3, 3]))
        lc = sa.cfg.loop_closure
        if rec.correction_m > lc.max_correction:
            return rec.reject("correction", f"correction {rec.correction_m:.3f} m > max_correction "
                                            f"{lc.max_correction} (cloud route)")
        rec.accepted, rec.reason_code, rec.reason = True, "accepted", f"accepted [cloud/{out.method}]"
        self.inter.append(loop)
        return rec
