"""How the team server joins two agents' frames (slam.dense.team.server.Server): only on two mutually consistent
verified loops that share no keyframe (server.join_min_loops, join_tolerance_*), a waiting loop that disagrees
with the joined frames refused, and a join undone when every loop supporting it is rejected later.

Frames: agent a's keyframe k sits at `server.global_pose(a, k)` in its component's frame; a component is a set of
agents linked by accepted inter-agent loops, in the frame of its lowest-numbered agent (`AgentSlot.component`,
`AgentSlot.T_global_world`). An InterLoop's T_ij is keyframe j's camera (agent_j) in keyframe i's (agent_i).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from swarmsplat.kernels import se3

from swarmsplat.slam.dense.loops.loop_log import LoopRecord
from swarmsplat.slam.dense.submaps import Keyframe

if TYPE_CHECKING:
    from .server import InterLoop

_rigid = se3.project_rigid


class JoinRules:
    """The join rules, mixed into the Server (they read its slots, cfg, inter, pending, rejected_edges and
    global_pose)."""

    def _alignment(self, L: InterLoop, moving: int) -> np.ndarray:
        """The alignment [4, 4] that loop L implies from component `moving`'s frame into the other component's
        (x_other = C x_moving), from the two keyframes' current poses in their components."""
        gi = self.global_pose(L.agent_i, self._kf(L.agent_i, L.kf_i))
        gj = self.global_pose(L.agent_j, self._kf(L.agent_j, L.kf_j))
        C = gi @ L.T_ij @ se3.inverse(gj)  # j's component -> i's
        return C if self.slots[L.agent_j].component == moving else se3.inverse(C)

    def _kf(self, a: int, kf_id: int) -> Keyframe:
        return self.slots[a].agent.keyframes[kf_id]

    def _end_in(self, L: InterLoop, component: int) -> tuple[int, Keyframe]:
        """(agent, keyframe) of loop L's end that lies in `component`."""
        if self.slots[L.agent_j].component == component:
            return L.agent_j, self._kf(L.agent_j, L.kf_j)
        return L.agent_i, self._kf(L.agent_i, L.kf_i)

    def _agree(self, L: InterLoop, P: InterLoop) -> tuple[bool, str]:
        """Whether loops L and P (between the same two components) imply the same alignment: the two alignments
        map each loop's keyframe in the moving component within server.join_tolerance_trans of each other and
        differ by at most join_tolerance_deg. Independent evidence only: the two loops share no keyframe."""
        if {(L.agent_i, L.kf_i), (L.agent_j, L.kf_j)} & {(P.agent_i, P.kf_i), (P.agent_j, P.kf_j)}:
            return False, "shares a keyframe"
        moving = self.slots[L.agent_j].component
        CL, CP = self._alignment(L, moving), self._alignment(P, moving)
        pts = [self.global_pose(*self._end_in(X, moving))[:3, 3] for X in (L, P)]
        dt = max(float(np.linalg.norm((CL[:3, :3] - CP[:3, :3]) @ p + CL[:3, 3] - CP[:3, 3])) for p in pts)
        dr = float(np.degrees(se3.rotation_angle(CL[:3, :3].T @ CP[:3, :3])))
        ok = dt <= self.cfg.join_tolerance_trans and dr <= self.cfg.join_tolerance_deg
        return ok, f"{100 * dt:.1f} cm / {dr:.2f} deg"

    def _join_or_wait(self, L: InterLoop, method: str) -> LoopRecord:
        """A verified loop between agents in different frames: join their components when it agrees with an
        earlier such loop (server.join_min_loops = 2; with 1 it joins at once), else keep it pending."""
        rec = L.record
        ci, cj = self.slots[L.agent_i].component, self.slots[L.agent_j].component
        partner, why = None, ""
        if self.cfg.join_min_loops > 1:
            for P in self.pending:
                if {self.slots[P.agent_i].component, self.slots[P.agent_j].component} != {ci, cj}:
                    continue
                ok, why = self._agree(L, P)
                if ok:
                    partner = P
                    break
            if partner is None:
                self.pending.append(L)
                return rec.reject("unconfirmed", f"verified [{method}] between agents in different frames; waiting "
                                                 f"for a second, consistent loop before joining them")
        b, a = L.agent_i, L.agent_j
        self._join(b, self._kf(b, L.kf_i), a, self._kf(a, L.kf_j), L.T_ij)
        self.joins += 1
        rec.joined = True
        rec.accepted, rec.reason_code = True, "accepted"
        rec.reason = f"accepted (joined frames) [{method}]" + (f"; agrees with loop {partner.record.query_agent}:"
                                                                f"{partner.record.query_kf} within {why}"
                                                                if partner else "")
        self.inter.append(L)
        if partner is not None:
            self.pending.remove(partner)
            partner.record.accepted, partner.record.reason_code = True, "accepted"
            partner.record.reason = "accepted (confirmed the join)"
            self.inter.append(partner)
        self._settle_pending()
        return rec

    def _settle_pending(self) -> None:
        """Pending loops whose agents a join has just put in one frame: kept as loops when they agree with the
        joined frames (within join_tolerance), else rejected as inconsistent with the join."""
        lc = self.slots[0].agent.cfg.loop_closure
        for P in list(self.pending):
            if self.slots[P.agent_i].component != self.slots[P.agent_j].component:
                continue
            self.pending.remove(P)
            T_now = se3.inverse(self.global_pose(P.agent_i, self._kf(P.agent_i, P.kf_i))) @ \
                self.global_pose(P.agent_j, self._kf(P.agent_j, P.kf_j))
            D = se3.inverse(T_now) @ P.T_ij
            dt, dr = float(np.linalg.norm(D[:3, 3])), float(np.degrees(se3.rotation_angle(D[:3, :3])))
            P.record.correction_m = dt
            if dt <= max(self.cfg.join_tolerance_trans, lc.max_correction) and dr <= self.cfg.join_tolerance_deg:
                P.record.accepted, P.record.reason_code, P.record.reason = True, "accepted", "accepted (after the join)"
                self.inter.append(P)
            else:
                P.record.reject("inconsistent", f"inconsistent with the joined frames: {100 * dt:.1f} cm / "
                                                f"{dr:.2f} deg")

    def _split_unsupported(self) -> int:
        """Undo joins that lost every loop supporting them (rejected after optimisation, by GNC or by the move
        check): agents are regrouped by the inter-agent loops still active, and a group cut off from its old
        component's root takes its lowest agent as its own root (frames re-expressed, poses unchanged). Returns
        how many components were split off."""
        n = len(self.slots)
        root = list(range(n))

        def find(x):
            while root[x] != x:
                root[x] = root[root[x]]
                x = root[x]
            return x

        for k, L in enumerate(self.inter):
            if not L.rejected and ("inter", k) not in self.rejected_edges:
                ra, rb = find(L.agent_i), find(L.agent_j)
                root[max(ra, rb)] = min(ra, rb)
        groups: dict[int, list[int]] = {}
        for a in range(n):
            groups.setdefault(find(a), []).append(a)
        split = 0
        for r, members in groups.items():
            if self.slots[r].component == r:  # still its component's root: its members keep their frames
                continue
            split += 1
            T_r = se3.inverse(self.slots[r].T_global_world)
            for a in members:
                self.slots[a].T_global_world = _rigid(T_r @ self.slots[a].T_global_world)
                self.slots[a].component = r
        self.joins_undone += split
        return split

    def _join(self, b: int, m: Keyframe, a: int, q: Keyframe, T_m_q: np.ndarray) -> None:
        """Bring the components of agents a and b into one frame, the one of the lower-numbered root."""
        ca, cb = self.slots[a].component, self.slots[b].component
        if cb < ca:  # a's component moves into b's frame: G_a(q) must become G_b(m) T_m_q
            C = self.global_pose(b, m) @ T_m_q @ se3.inverse(self.global_pose(a, q))
            moving, root = ca, cb
        else:
            C = self.global_pose(a, q) @ se3.inverse(T_m_q) @ se3.inverse(self.global_pose(b, m))
            moving, root = cb, ca
        for s in self.slots:
            if s.component == moving:
                s.T_global_world = _rigid(C @ s.T_global_world)
                s.component = root
