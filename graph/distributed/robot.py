"""One robot of the distributed solver: its own poses and loop scales, its neighbours' latest separators, a step.

The robot's part of the objective is every factor that touches one of its poses: its odometry, its intra-robot
loops and each inter-robot loop it shares (graph.distributed.partition). A step minimises that part over the
robot's own poses and the scales of its loops (both robots of a loop hold every factor on its scale, so either may
move it: a scale free in one robot's step only zig-zags against the other's poses), with its neighbours' poses
held at the latest values they sent (a few Levenberg-Marquardt iterations of graph.solvers on a
graph.formulations problem, warm started): block-coordinate descent, in which every step lowers the team's
objective. The robot then moves omega times that step (over-relaxation), omega adapted to how fast its steps
shrink (`_adapt`: near 1 where the team converges fast, up to 1.9 on long chains of robots, where plain
block-coordinate descent crawls); `Settings.relax` 1 keeps plain descent (monotone). The team's shared scale (formulation `shared`) is held fixed in the step; its consensus terms
(gradient and Gauss-Newton curvature of the robot's owned loops) go to the keeper, the lowest-numbered robot,
which takes the Newton step and sends the new value. GNC weights of the owned loops are set by `gnc_update` from
the loops' costs at the current estimate and travel with the estimates.

Messages are idempotent and ordered by stamp: a neighbour's estimate replaces what the robot holds only if it is
newer, so lost, duplicated and reordered messages never corrupt the state; a silent neighbour's last estimate is
held fixed (the rest of the team keeps converging), and a robot that returns picks up the latest estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from .. import lie
from ..formulations import build_problem, initial_scales
from ..pose_graph import Edge, PoseGraph
from ..scale_factors import is_residuals, is_residuals_network
from ..solvers import SCALE_MIN, levenberg_marquardt, loop_costs
from .delta import Received, Sent
from .gnc_plan import GncPlan
from .messages import FLAG_BINARY, FLAG_DELTA, FLAG_SCALARS, FLAG_STILL, Estimate
from .partition import RobotPart

OMEGA_MAX = 1.9
HOLD_SIGMA = 1e-6  # neighbours' poses and scales are held by priors this stiff (the anchors' sigma)


@dataclass
class Settings:
    """The formulation (graph.formulations.build_problem's arguments) and the step's own knobs."""

    formulation: str = "base"
    scale_init: str = "odometry"
    cluster_gap: int = 10
    scale_sigma: float = 0.05
    scale_prior_sigma: float = 10.0
    scale_residual: str = "metric"
    objective: str = "g2o"
    local_iterations: int = 3  # LM iterations per step
    still_tol: float = 1e-6  # a step that lowers the robot's part by less than this (relative) is still
    still_atol: float = 1e-12  # ... or by less than this (absolute): a part at zero error (odometry alone, say)
    # moves it by rounding only, relatively by any amount
    shared_s0: float = 1.0  # the shared scale's initial value (median of the loops' initial scales)
    relax: float = 0.0  # over-relaxation: the step moves own poses and scales this many times the local update;
    # 0: adapted to the robot's observed rate of convergence (RobotSolver._adapt)
    delta: bool = True  # separator poses as float16 twists from the neighbour's last held estimate
    # (graph.distributed.delta); False: absolute float32 poses in every estimate
    sparse_tol: float = 1e-3  # a separator twist below this (radians; times the part's median edge length for
    # translation) in every component goes as zero, and the estimate lists only the others (FLAG_SPARSE)
    gnc_plan: GncPlan | None = None  # GNC on a fixed schedule, decided by each robot at its step
    # (graph.distributed.gnc_plan: robot processes); None: the team drives GNC (graph.distributed.team)


class RobotSolver:
    """Pure per-robot state; `step()` returns the estimates to send, `receive()` takes one."""

    def __init__(self, part: RobotPart, edges: dict[int, Edge], poses: dict[int, np.ndarray],
                 settings: Settings, gt_scales: dict[int, float] | None = None):
        """`edges`: the team-graph edges of `part.edges` (index -> Edge); `poses`: initial T_world_kf of the
        robot's own keys; `gt_scales` (scale_init 'gt'): team edge index -> scale."""
        self.part, self.settings = part, settings
        self.robot = part.robot
        self.edge_ids = list(part.edges)
        self.edges = [edges[n] for n in self.edge_ids]
        self.gt = None if gt_scales is None else {i: gt_scales[n] for i, n in enumerate(self.edge_ids) if n in gt_scales}
        self.poses = {k: np.asarray(poses[k], float) for k in part.keys}
        self.nb_poses: dict[int, np.ndarray] = {}
        self.nb_stamp: dict[int, int] = {}
        s0 = initial_scales(PoseGraph({}, self.edges), settings.scale_init, self.gt)
        self.scales = {self.edge_ids[i]: s for i, s in s0.items()}  # own and (until heard) neighbours' loops
        self.weights = {n: 1.0 for n, e in zip(self.edge_ids, self.edges) if e.kind != "odometry"}
        self.shared = settings.shared_s0
        self.shared_stamp = 0
        self.terms: dict[int, tuple[float, float]] = {}  # robot -> its shared-scale (g, H), relayed to all
        self.term_stamp: dict[int, int] = {}  # robot -> the stamp of the step its terms come from
        self.mu0: dict[int, float] = {}  # robot -> the smallest GNC mu0 proposal it has heard of
        self.still = False
        self.omega = 1.0  # over-relaxation in use when relax is 0 (_adapt)
        self._steps: list[float] = []
        self._last_cost = float("inf")
        self._rises = 0  # consecutive steps that started from a higher cost of the part than the one before
        self.stamp = 0
        self.heard: dict[int, int] = {}  # robot -> step count of ours when we last heard it
        self.nb_still: dict[int, bool] = {}
        self.gnc = False  # weights travel with the estimates once GNC runs
        self.refused = 0  # estimates dropped for counts other than expected
        self.baseless = 0  # relative estimates dropped because their base is not held
        lengths = [float(np.linalg.norm(e.T_ij[:3, 3])) for e in self.edges if not e.up_to_scale]
        length = float(np.median(lengths)) if lengths else 1.0
        self._tx, self._rx = Sent((settings.sparse_tol, settings.sparse_tol * length)), Received()
        self._owner = {n: min(e.key_i >> 56, e.key_j >> 56) for n, e in zip(self.edge_ids, self.edges)}
        self._scaled = {n: e.up_to_scale for n, e in zip(self.edge_ids, self.edges)}
        self._sent: dict[tuple[int, int], tuple[list[int], list[int]]] = {}
        own = set(part.keys)
        self._expect: dict[int, list[int]] = {}  # neighbour -> its poses our edges touch (its separators for us)
        for e in self.edges:
            for k in (e.key_i, e.key_j):
                if k not in own:
                    self._expect.setdefault(k >> 56, set()).add(k)
        self._expect = {q: sorted(s) for q, s in self._expect.items()}

    # --------------------------------------------------------------------------------------- the step
    def local_problem(self):
        """The robot's part as a graph.formulations Problem (neighbours' poses and scales held), its weights
        (local edge index -> w) and the local -> team edge index map."""
        s = self.settings
        poses = dict(self.poses)
        poses.update(self.nb_poses)
        use = [i for i, e in enumerate(self.edges) if e.key_i in poses and e.key_j in poses]
        G = PoseGraph({k: poses[k] for k in poses}, [self.edges[i] for i in use])
        ids = [self.edge_ids[i] for i in use]
        gt = None if self.gt is None else {m: self.gt[i] for m, i in enumerate(use) if i in self.gt}
        held = sorted(self.nb_poses)
        problem = build_problem(G, s.formulation, s.scale_init, gt_scales=gt, cluster_gap=s.cluster_gap,
                                scale_sigma=s.scale_sigma, scale_prior_sigma=s.scale_prior_sigma,
                                scale_residual=s.scale_residual, objective=s.objective,
                                anchors=self.part.anchors + held)
        if problem.scale_loops is not None:
            hold = gtsam.noiseModel.Isotropic.Sigma(1, HOLD_SIGMA)
            done = set()
            for m, k in zip(problem.scale_loops.edge, problem.scale_loops.key_s):
                n, k = ids[int(m)], int(k)
                if k in done:
                    continue
                done.add(k)
                if s.formulation == "shared":
                    value, held_scale = self.shared, True
                else:
                    value, held_scale = self.scales[n], False  # both robots of a loop hold every factor on it
                problem.initial.update(k, float(value))
                if held_scale:
                    problem.fixed.add(gtsam.PriorFactorDouble(k, float(value), hold))
        weights = {m: self.weights.get(n, 1.0) for m, n in enumerate(ids)}
        return problem, weights, ids

    def step(self) -> list[Estimate]:
        """Minimise the robot's part (a few LM iterations) and return one estimate per neighbour."""
        self.stamp += 1
        plan = self.settings.gnc_plan
        if plan is not None:
            self._follow(plan, self.stamp)
        problem, weights, ids = self.local_problem()
        res = levenberg_marquardt(problem, weights=weights, max_iterations=self.settings.local_iterations)
        # A robot whose edges touch no other robot's poses solves its whole connected group in its step: that is
        # Gauss-Seidel on one block, exact but for LM's own iterations, and over-relaxing it only overshoots (the
        # step lengths still shrink at LM's rate, which _adapt takes for a slow chain: an isolated robot of a
        # 3-robot team then oscillated around its optimum for 300 rounds and was never still).
        w = self.settings.relax if self.settings.relax > 0 else self.omega if self.part.neighbours else 1.0
        keys = self.part.keys
        old = np.stack([self.poses[k] for k in keys])
        xi = lie.log(lie.between(old, np.stack([res.poses[k] for k in keys])))
        new = old @ lie.exp(w * xi)
        for k, T in zip(keys, new):
            self.poses[k] = T
        if self.settings.relax <= 0 and self.part.neighbours:
            self._adapt(w * float(np.linalg.norm(xi)), res.initial_error)
        for m, v in res.scales.items():
            if self.settings.formulation != "shared":
                n = ids[m]
                self.scales[n] = max(self.scales[n] + w * (float(v) - self.scales[n]), SCALE_MIN)
        drop = res.initial_error - res.final_error
        self.still = drop <= max(self.settings.still_tol * res.initial_error, self.settings.still_atol)
        if self.settings.formulation == "shared" and problem.scale_loops is not None:
            self.terms[self.robot] = self._shared_terms(problem, res.values, weights, ids)
            self.term_stamp[self.robot] = self.stamp
            if self.is_keeper():
                self._shared_newton()
        return self.messages(scalars=True if plan is not None and plan.relays(self.stamp) else None)

    def _follow(self, plan: GncPlan, k: int) -> None:
        """What a GNC plan has this robot do at its step in round k, from what it holds now."""
        if plan.proposes(k):
            self.propose_mu0(plan.barc)
        j = plan.gnc_step(k)
        if j is not None:
            mu0 = self.team_mu0()
            if mu0 > 0:
                self.gnc_update(mu0 * plan.mu_step ** j, plan.barc)

    def _adapt(self, d: float, cost: float) -> None:
        """Successive over-relaxation's optimal omega from the rate at which this robot's steps shrink (`d`: the
        length of the step just taken). For a Gauss-Seidel sweep of spectral radius mu^2, SOR with omega shrinks the
        error by lambda, (lambda + omega - 1)^2 = lambda omega^2 mu^2, and converges fastest at
        omega = 2 / (1 + sqrt(1 - mu^2)) (Hageman & Young's adaptive SOR); lambda is the median of the last three
        ratios of step lengths. A fast-converging robot (small ratios) stays near 1, a slow chain of robots goes
        towards OMEGA_MAX."""
        h = self._steps
        self._rises = self._rises + 1 if cost > self._last_cost else 0
        self._last_cost = cost
        if self._rises >= 3 and self.omega > 1.0:  # overshoot: plain descent, measure the rate again (restart)
            self.omega, h[:] = 1.0, []
        h.append(d)
        if len(h) < 4 or min(h[-4:-1]) <= 0:
            return
        lam = float(np.median([h[-1] / h[-2], h[-2] / h[-3], h[-3] / h[-4]]))
        if not 0 < lam < 1:
            return
        w = self.omega
        mu2 = min((lam + w - 1) ** 2 / (lam * w * w), 0.9999)
        self.omega = float(min(2.0 / (1.0 + np.sqrt(1.0 - mu2)), OMEGA_MAX))

    def messages(self, scalars: bool | None = None) -> list[Estimate]:
        """This robot's current estimate for each neighbour (with the consensus scalars, when `scalars`, also for
        every robot it has heard of)."""
        out = []
        scalars = self.settings.formulation == "shared" if scalars is None else scalars
        flags = (FLAG_STILL if self.still else 0) | (FLAG_BINARY if self.binary() else 0)
        for q in self.part.neighbours:
            keys = self.part.separators[q]
            msg = Estimate(self.robot, q, self.stamp, np.stack([self.poses[k] for k in keys]) if keys
                           else np.zeros((0, 4, 4)), flags=flags)
            sc, wt = self._sent_loops(q, self.robot)
            msg.scales = np.array([self.scales[n] for n in sc])
            if self.gnc:
                msg.weights = np.array([self.weights.get(n, 1.0) for n in wt])
            msg.ack = self._rx.ack(q)
            if self.settings.delta:
                self._tx.encode(msg, tuple(keys))
                if self.gnc:
                    self._tx.encode_weights(msg)
            out.append(msg)
        if scalars:
            for q in sorted(set(self.part.neighbours) | set(self.heard)):
                if q == self.robot:
                    continue
                m = next((m for m in out if m.recipient == q), None)
                if m is None:
                    m = Estimate(self.robot, q, self.stamp, flags=flags)
                    out.append(m)
                m.flags |= FLAG_SCALARS
                g, h = self.terms.get(self.robot, (0.0, 0.0))
                m.shared_g, m.shared_h, m.shared_s, m.shared_stamp = g, h, self.shared, self.shared_stamp
                m.mu0 = self.team_mu0()  # the smallest proposal heard: relayed, it reaches every robot
                m.relayed = [(r, self.term_stamp[r], *self.terms[r]) for r in sorted(self.terms)
                             if r not in (self.robot, q)]
        return out

    def _sent_loops(self, q: int, sender: int) -> tuple[list[int], list[int]]:
        """The loops of pair (self, q) whose scale and weight `sender` sends: those it owns, in pair order."""
        key = (q, sender)
        if key not in self._sent:
            pair = self.part.pair_loops.get(q, [])
            mine = [n for n in pair if self._owner[n] == sender]
            scaled = [n for n in pair if self.settings.formulation in ("is", "ss") and self._scaled[n]]
            self._sent[key] = (scaled, mine)
        return self._sent[key]

    def receive(self, msg: Estimate) -> bool:
        """Take a neighbour's estimate if it is newer than what we hold and has the counts we expect; returns
        whether it was taken."""
        q = msg.sender
        if q == self.robot or msg.recipient != self.robot:
            return False
        self.heard[q] = self.stamp
        if msg.flags & FLAG_SCALARS:
            for r, stamp, g, h in [(q, msg.stamp, msg.shared_g, msg.shared_h)] + list(msg.relayed):
                if r != self.robot and stamp >= self.term_stamp.get(r, -1):
                    self.terms[r], self.term_stamp[r] = (g, h), stamp
            if msg.mu0 > 0:  # the smallest a sender ever relayed (a late resend carries an older, larger one)
                self.mu0[q] = min(self.mu0.get(q, msg.mu0), msg.mu0)
            if msg.shared_stamp > self.shared_stamp:
                self.shared, self.shared_stamp = msg.shared_s, msg.shared_stamp
        if msg.stamp <= self.nb_stamp.get(q, -1):
            return False
        self._tx.heard(q, msg.stamp, msg.ack)
        keys = self._expect.get(q, [])
        sc, wt = self._sent_loops(q, q)
        P = len(msg.delta) if msg.flags & FLAG_DELTA else len(msg.poses)
        if (P and P != len(keys)) or len(msg.scales) not in (0, len(sc)) or len(msg.weights) not in (0, len(wt)):
            self.refused += 1
            return False
        if not P and keys:  # a scalars-only message: not an estimate of the poses
            return False
        if not self._rx.decode(msg, tuple(keys)):
            self.baseless += 1
            return False
        self.nb_stamp[q] = msg.stamp
        for k, T in zip(keys, msg.poses):
            self.nb_poses[k] = T
        for n, v in zip(sc, msg.scales.tolist()):
            self.scales[n] = v
        for n, v in zip(wt, msg.weights.tolist()):
            self.weights[n] = v
        self.nb_still[q] = bool(msg.flags & FLAG_STILL)
        return True

    # --------------------------------------------------------------------------------------- shared scale
    def is_keeper(self, alive: set[int] | None = None) -> bool:
        """The lowest-numbered robot among those heard of recently (directly, or through relayed terms) keeps the
        shared scale."""
        if alive is None:
            lag = 3 + len(self.term_stamp)  # relayed terms are a hop behind per robot on the way
            recent = {q for q, t in self.heard.items() if self.stamp - t <= 3}
            recent |= {q for q, s in self.term_stamp.items() if s >= self.stamp - lag}
        else:
            recent = alive
        return all(self.robot < q for q in recent if q != self.robot)

    def _shared_terms(self, problem, values, weights, ids) -> tuple[float, float]:
        """This robot's consensus terms for the shared scale: gradient and Gauss-Newton curvature of its owned loops'
        cost in it (each loop counted once in the team's sum)."""
        sl = problem.scale_loops
        own = np.array([ids[int(m)] in self.part.owned for m in sl.edge])
        if not own.any():
            return 0.0, 0.0
        Ti = np.stack([values.atPose3(int(k)).matrix() for k in sl.key_i[own]])
        Tj = np.stack([values.atPose3(int(k)).matrix() for k in sl.key_j[own]])
        s = np.full(int(own.sum()), self.shared)
        fn = is_residuals_network if sl.residual == "network" else is_residuals
        e, _, _, Hs = fn(Ti, Tj, s, sl.R_meas[own], sl.t_meas[own])
        w = np.array([weights.get(int(m), 1.0) for m in sl.edge[own]])
        W = sl.sqrt_info[own] * np.sqrt(w)[:, None, None]
        r = np.einsum("lab,lb->la", W, e)
        J = np.einsum("lab,lb->la", W, Hs)
        return float(np.sum(J * r)), float(np.sum(J * J))

    def _shared_newton(self) -> None:
        sp = self.settings.scale_prior_sigma
        g = sum(t[0] for t in self.terms.values()) + (self.shared - self.settings.shared_s0) / sp**2
        h = sum(t[1] for t in self.terms.values()) + 1.0 / sp**2
        self.shared = max(self.shared - g / h, SCALE_MIN)
        self.shared_stamp += 1

    # --------------------------------------------------------------------------------------- GNC
    def owned_loop_costs(self) -> dict[int, float]:
        """Unweighted cost of every loop this robot owns at the current estimate (team edge index -> cost)."""
        problem, _, ids = self.local_problem()
        costs = loop_costs(problem, problem.initial)
        return {ids[m]: c for m, c in costs.items() if ids[m] in self.part.owned}

    def propose_mu0(self, barc: float) -> float:
        """GNC's initial mu from the owned loops' residuals (graph.solvers.gnc's rule); the team takes the
        smallest proposal."""
        c = np.array(list(self.owned_loop_costs().values()))
        pos = c[2 * c - barc > 0] if len(c) else c
        mu = float(np.min(barc / (2 * pos - barc))) if len(pos) else 0.0
        self.mu0[self.robot] = mu
        return mu

    def team_mu0(self) -> float:
        vals = [v for v in self.mu0.values() if v > 0]
        return max(min(vals), 1e-6) if vals else 0.0

    def gnc_update(self, mu: float, barc: float) -> None:
        """TLS weights of the owned loops at the current estimate (graph.solvers.gnc's update)."""
        self.gnc = True
        costs = self.owned_loop_costs()
        upper, lower = (mu + 1) / mu * barc, mu / (mu + 1) * barc
        for n, c in costs.items():
            if c >= upper:
                w = 0.0
            elif c <= lower:
                w = 1.0
            else:
                w = float(np.clip(np.sqrt(barc * mu * (mu + 1) / max(c, 1e-300)) - mu, 0.0, 1.0))
            self.weights[n] = w

    def binary(self, tol: float = 1e-4) -> bool:
        return all(abs(self.weights.get(n, 1.0) - round(self.weights.get(n, 1.0))) <= tol for n in self.part.owned)
