"""A swarm robot's part of the distributed pose-graph solver (`swarm.solver: distributed`): no robot gathers the
team's graph; each solves its own part and sends each neighbour only the separator poses it needs.

What a robot solves is what it holds anyway: its keyframes' odometry and the loops it shares with each robot (the
lower-id robot of a pair registers them and sends them over, node.py). Its part is its poses, its odometry and every
loop touching it (graph.distributed.partition on that graph); the state and the step are graph.distributed.robot's,
the same as in the simulated team and in the robot processes of `graph solve --distributed --processes`. Estimates
travel as `messages.DistributedEstimate` (a graph.distributed estimate and the root of the sender's frame).

Frames: a robot starts in its own odometry frame, as the root of its frame. A robot that hears a lower root moves
its poses into that frame through the best loop it shares with the sender (its translation scaled by eq. 6, as the
gather's initial estimate does) and forgets what it held of robots in other frames, so a connected group ends in
the odometry frame of its lowest robot, as the elected robot's solve does; the root holds its first keyframe.

Schedule: at most one step a tick. A robot steps once each neighbour in range and in its frame with a lower id has
sent an estimate newer than its own and each one with a higher id has sent its latest (Gauss-Seidel in id order, so
neighbours never step at once and every step lowers the team's cost); a robot behind its neighbours jumps its
stamp forward; a neighbour heard from within `wait` ticks is waited for, then held at its last estimate. While it
waits, the robot resends its estimate every `resend` ticks. When its graph changes (keyframes, loops) the part is
built again from the current poses (new keyframes chained by odometry), its loops' scales kept.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.graph.distributed.messages import Estimate
from swarmsplat.graph.distributed.partition import partition
from swarmsplat.graph.distributed.robot import RobotSolver, Settings
from swarmsplat.graph.pose_graph import PoseGraph, robot_key
from swarmsplat.kernels.errors import InputError

from . import messages as M
from .optimiser import SolveConfig, robot_char

FORMULATIONS = ("base", "is", "ss")  # the shared scale needs team-wide consensus terms the swarm does not relay


def check_solve_config(cfg: SolveConfig) -> None:
    if cfg.solver == "distributed" and cfg.formulation not in FORMULATIONS:
        raise InputError(f"swarm.solver distributed solves the formulations {', '.join(FORMULATIONS)}; "
                         f"got {cfg.formulation!r}")


class SwarmPart:
    """One robot's part of the distributed solve inside a swarm node (module docstring)."""

    def __init__(self, node, wait: int = 3, resend: int = 2):
        check_solve_config(node.cfg.solve)
        self.node, self.me, self.wait, self.resend = node, node.id, wait, resend
        self.root = node.id
        self.solver: RobotSolver | None = None
        self.version = None
        self.keys: list[int] = []
        self.poses: dict[int, np.ndarray] = {}  # own key -> T_world_kf in the frame of `root`
        self.scales: dict[tuple[int, int], float] = {}  # loop (key_i, key_j) -> scale held (own or the owner's)
        self.got: dict[int, tuple[int, Estimate]] = {}  # robot -> (its root, its latest estimate to us)
        self.heard: dict[int, int] = {}  # robot -> tick of its latest estimate
        self.last_step: int | None = None  # tick of the last step (or of the first build)
        self.last_send = -(1 << 30)
        self.stamp = 0  # the solver's step counter, kept across rebuilds
        self.steps = 0
        self.still_steps = 0

    # ------------------------------------------------------------------------------------------ the part
    def graph(self) -> PoseGraph:
        """Own poses (current estimate; new keyframes chained by odometry), own odometry, every loop touching them
        (the other robots' keyframes as placeholder poses: the part holds them at what their robots send)."""
        n, cfg = self.node, self.node.cfg.solve
        c = robot_char(self.me)
        g = PoseGraph()
        odo = n.odometry
        prev = None
        for i, T_odo in enumerate(odo):
            k = robot_key(c, i)
            if k in self.poses:
                T = self.poses[k]
            elif prev is None:
                T = np.asarray(T_odo, float)
            else:
                T = prev @ np.linalg.inv(odo[i - 1]) @ T_odo
            g.add_pose(k, T)
            prev = T
        for i in range(len(odo) - 1):
            g.add_odometry(robot_key(c, i), robot_key(c, i + 1), np.linalg.inv(odo[i]) @ odo[i + 1], cfg.info(False))
        for (qa, qi, mb, mj), lp in sorted(n.own_loops().items()):
            if (qa == self.me and qi >= len(odo)) or (mb == self.me and mj >= len(odo)):
                continue
            ki, kj = robot_key(robot_char(qa), qi), robot_key(robot_char(mb), mj)
            for k in (ki, kj):
                if k not in g.poses:
                    g.add_pose(k)
            g.add_loop(ki, kj, lp.T_query_match, cfg.info(True), up_to_scale=True,
                       confidence=1.0 if cfg.uniform_noise else lp.confidence, odom_scale=lp.odom_scale)
        return g

    def rebuild(self) -> None:
        """The part of the current graph, from the current poses and scales; neighbours' latest estimates in this
        robot's frame taken again."""
        cfg = self.node.cfg.solve
        g = self.graph()
        part = partition(g)[ord(robot_char(self.me))]
        part.anchors = part.keys[:1] if self.root == self.me else []
        # plain descent: parts grow, neighbours come and go; absolute poses: a rebuilt part starts with no history of
        # what its neighbours hold, and a robot joining a frame reads an estimate's poses before its solver does
        settings = Settings(formulation=cfg.formulation, relax=1.0, delta=False)
        self.stamp = self.solver.stamp if self.solver is not None else self.stamp
        self.solver = RobotSolver(part, dict(enumerate(g.edges)), g.poses, settings)
        self.solver.stamp = self.stamp
        for m, e in enumerate(g.edges):
            if (e.key_i, e.key_j) in self.scales and m in self.solver.scales:
                self.solver.scales[m] = self.scales[(e.key_i, e.key_j)]
        self._edges = g.edges
        self.keys = part.keys
        self.poses = {k: g.poses[k] for k in part.keys}
        for q, (root, est) in sorted(self.got.items()):
            if root == self.root:
                self.solver.receive(est)

    def _keep(self) -> None:
        """Copy the solver's poses and scales out (they outlive a rebuild)."""
        s = self.solver
        self.poses = {k: s.poses[k] for k in self.keys}
        for m, v in s.scales.items():
            e = self._edges[m]
            self.scales[(e.key_i, e.key_j)] = v

    def _version(self):
        return (len(self.node.odometry), tuple(sorted(self.node.own_loops())), self.root)

    # ------------------------------------------------------------------------------------------ messages
    def on_message(self, sender: int, msg: M.DistributedEstimate) -> None:
        try:
            est = Estimate.from_bytes(msg.blob.tobytes())
        except InputError:
            return
        if est.sender != ord(robot_char(sender)) or est.recipient != ord(robot_char(self.me)):
            return
        self.got[sender] = (int(msg.root), est)
        self.heard[sender] = self.node.tick
        if msg.root < self.root:
            self._join(sender, int(msg.root), est)
        elif msg.root == self.root and self.solver is not None:
            self.solver.receive(est)

    def _join(self, sender: int, root: int, est: Estimate) -> None:
        """Move this robot's poses into the frame of `root` through the most confident loop shared with `sender`,
        whose pose `est` carries (the sender's separators for us, in key order)."""
        if self.solver is None:
            self.rebuild()
        keys = self.solver._expect.get(ord(robot_char(sender)), [])
        if len(keys) != len(est.poses) or not len(keys):
            return  # the two hold different loop sets for now: wait for the next estimate
        theirs = dict(zip(keys, est.poses))
        own = set(self.keys)
        best = None
        for e in self._edges:
            if e.kind != "loop" or not ({e.key_i, e.key_j} & own) or not ({e.key_i, e.key_j} & set(theirs)):
                continue
            if best is None or e.confidence > best.confidence:
                best = e
        if best is None:
            return
        T = best.T_ij.copy()
        T[:3, 3] *= best.odom_scale or 1.0
        if best.key_j in theirs:  # T_world_i = T_world_j T_ij^-1
            k, T_world_k = best.key_i, theirs[best.key_j] @ np.linalg.inv(T)
        else:
            k, T_world_k = best.key_j, theirs[best.key_i] @ T
        self._keep()
        self.stamp = self.solver.stamp
        D = T_world_k @ np.linalg.inv(self.poses[k])
        self.poses = {q: D @ T for q, T in self.poses.items()}
        self.root = root
        self.got = {q: v for q, v in self.got.items() if v[0] == root}
        self.solver = None
        self.version = None

    # ------------------------------------------------------------------------------------------ the tick
    def tick(self, tick: int, in_range: list[int]) -> None:
        """Rebuild the part if the graph changed; step if the schedule lets it (module docstring); send."""
        if len(self.node.odometry) == 0:
            return
        v = self._version()
        if v != self.version:
            if self.solver is not None:
                self._keep()
            self.rebuild()
            self.version = v
            self._send(tick, self.solver.messages(scalars=False))
        s = self.solver
        me = ord(robot_char(self.me))
        active = [q for q in s.part.neighbours if q - ord("a") in in_range
                  and self.got.get(q - ord("a"), (None,))[0] == self.root]
        lower = [q for q in active if q < me]
        higher = [q for q in active if q > me]
        ready = all(s.nb_stamp.get(q, -1) > s.stamp for q in lower) and \
            all(s.nb_stamp.get(q, -1) >= s.stamp for q in higher)
        self.last_step = tick if self.last_step is None else self.last_step
        if not ready and tick - self.last_step < self.wait:
            if tick - self.last_send >= self.resend:
                self._send(tick, s.messages(scalars=False))
            return
        k = max([s.stamp + 1] + [s.nb_stamp.get(q, 0) for q in lower] + [s.nb_stamp.get(q, -1) + 1 for q in higher])
        s.stamp = k - 1
        msgs = s.step()
        self.stamp = s.stamp
        self.steps += 1
        self.still_steps = self.still_steps + 1 if s.still else 0
        self.last_step = tick
        self._keep()
        self._send(tick, msgs)

    def _send(self, tick: int, msgs: list[Estimate]) -> None:
        self.last_send = tick
        for m in msgs:
            self.node.tx.send(m.recipient - ord("a"), M.DistributedEstimate(
                root=self.root, blob=np.frombuffer(m.to_bytes(), np.uint8)))

    # ------------------------------------------------------------------------------------------ state
    def settled(self, in_range: list[int]) -> bool:
        """Built on the current graph, its last two steps still, and every neighbour in range in its frame and
        still."""
        s = self.solver
        if s is None or self.version != self._version() or self.still_steps < 2:
            return False
        for q in s.part.neighbours:
            r = q - ord("a")
            if r in in_range and (self.got.get(r, (None,))[0] != self.root or not s.nb_still.get(q, False)):
                return False
        return True

    def trajectory(self) -> np.ndarray:
        """T_world_kf [n_kf, 4, 4] of this robot's keyframes in its frame (new keyframes chained by odometry)."""
        g = self.graph()
        c = robot_char(self.me)
        return np.stack([g.poses[robot_key(c, i)] for i in range(len(self.node.odometry))])

    def loop_scales(self) -> dict[tuple[int, int], float]:
        """Scale of each up-to-scale loop this robot owns, by its (key_i, key_j)."""
        if self.solver is None:
            return {}
        owned = {(self._edges[m].key_i, self._edges[m].key_j) for m in self.solver.part.owned}
        return {k: v for k, v in self.scales.items() if k in owned}
