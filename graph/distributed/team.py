"""A team of distributed-solver robots run in one process: the schedule, the message delivery (with faults), the
GNC outer loop, and the figures (the team's cost per round, bytes).

One round: robots update colour by colour (graph.distributed.partition; neighbours never update at once), each
robot's estimates delivered before the next colour. The team stops when every robot present reports its last
step still (FLAG_STILL) for two rounds in a row, or after `max_rounds`. The driver evaluates the team's
objective after every round with the centralised problem (graph.formulations, the same objective), for the
figures only: the robots never see it.

Faults (`Faults`): each message lost with probability `drop`, sent twice with `duplicate`, delivered in a shuffled
order (`reorder`), a robot leaving at a round (its part then stays at its last estimate) and returning at a later
one. GNC: the robots first run `ls_rounds` rounds with all weights 1; each proposes GNC's initial mu from its own loops
and the team takes the smallest; then each GNC step updates the owned loops' weights and runs rounds until still
(at most `gnc_rounds`), mu growing by `mu_step`, until every robot's weights are binary.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from swarmsplat.kernels.errors import InputError

from ..formulations import Problem, build_problem, initial_scales, pose_values
from ..pose_graph import PoseGraph
from ..solvers import _ScaleTerm, inlier_threshold, tls_objective
from .messages import POSE_BYTES, Estimate
from .partition import partition, robot_of
from .robot import RobotSolver, Settings

EDGE_BYTES = 10 + 24 + 84  # two (robot, index) ids, the relative pose, the 21-entry information matrix (float32)
GATHER_POSE_BYTES = 4 + POSE_BYTES  # a keyframe index and the pose


@dataclass
class Faults:
    drop: float = 0.0
    duplicate: float = 0.0
    reorder: bool = False
    leave: dict[int, int] = field(default_factory=dict)  # robot -> round it leaves at
    back: dict[int, int] = field(default_factory=dict)  # robot -> round it returns at
    seed: int = 0


@dataclass
class DistributedResult:
    poses: dict[int, np.ndarray]
    scales: dict[int, float]  # up-to-scale loop edge -> scale (its owner's)
    weights: dict[int, float]  # loop edge -> GNC weight (its owner's)
    rejected: list[int]
    rounds: int
    history: list[float]  # the team's objective after each round (index 0: the initial estimate)
    bytes_history: list[int]  # bytes sent up to the end of each round
    initial_error: float
    final_error: float
    bytes_total: int
    pose_sends: int  # separator poses sent, summed over messages
    gather_bytes: int  # what gathering the graph on one robot and broadcasting its estimate would send
    robots: int
    groups: list[list[int]]  # robots per connected component
    converged: bool
    time_s: float
    gnc_iterations: int = 0
    tls_error: float | None = None  # GNC: the truncated-least-squares objective (graph.solvers.tls_objective)

    @property
    def bytes_per_separator_iteration(self) -> float:
        return self.bytes_total / max(self.pose_sends, 1)

    def rounds_to(self, reference: float, rel: float) -> int | None:
        """First round whose cost is within `rel` of `reference` (None: never)."""
        return next((i for i, c in enumerate(self.history) if c <= reference * (1 + rel)), None)

    def bytes_to(self, reference: float, rel: float) -> int | None:
        r = self.rounds_to(reference, rel)
        return None if r is None else self.bytes_history[r]


def shared_s0(graph: PoseGraph, settings: Settings, gt_scales=None) -> float:
    s0 = initial_scales(graph, settings.scale_init, gt_scales)
    return float(np.median(list(s0.values()))) if s0 else 1.0


def gather_bytes(graph: PoseGraph) -> int:
    """Bytes of the elected-robot way with this module's encodings: every robot but the lowest sends its poses
    (initial values) and the edges it owns; the elected robot sends every pose back to each of them."""
    parts = partition(graph)
    elected = min(parts)
    sent = 0
    for r, p in parts.items():
        if r == elected:
            continue
        owned = [n for n in p.edges if min(robot_of(graph.edges[n].key_i), robot_of(graph.edges[n].key_j)) == r]
        sent += GATHER_POSE_BYTES * len(p.keys) + EDGE_BYTES * len(owned)
    return sent + GATHER_POSE_BYTES * len(graph.poses) * (len(parts) - 1)


class Team:
    """Simulated robots with an in-process message queue (module docstring)."""

    def __init__(self, graph: PoseGraph, settings: Settings, *, initial_poses=None, gt_scales=None,
                 faults: Faults | None = None):
        if any((k >> 56) == 0 for k in graph.poses):
            raise InputError("the distributed solver needs robot keys (GTSAM Symbols): one robot's plain integer "
                             "ids have no team to distribute over")
        self.graph, self.faults = graph, faults or Faults()
        poses = graph.poses if initial_poses is None else initial_poses
        settings.shared_s0 = shared_s0(graph, settings, gt_scales)
        self.settings = settings
        self.parts = partition(graph)
        edges = dict(enumerate(graph.edges))
        self.robots = {r: RobotSolver(p, edges, poses, settings, gt_scales) for r, p in self.parts.items()}
        self.problem: Problem = build_problem(graph, settings.formulation, settings.scale_init, initial_poses=poses,
                                              gt_scales=gt_scales, cluster_gap=settings.cluster_gap,
                                              scale_sigma=settings.scale_sigma,
                                              scale_prior_sigma=settings.scale_prior_sigma,
                                              scale_residual=settings.scale_residual, objective=settings.objective)
        self.rng = np.random.default_rng(self.faults.seed)
        self.queue: list[bytes] = []
        self.bytes_total = 0
        self.pose_sends = 0
        self.round = 0
        self.history: list[float] = []
        self.bytes_history: list[int] = []
        self.still_rounds = 0

    # ------------------------------------------------------------------------------------ network
    def present(self, r: int) -> bool:
        f = self.faults
        return not (r in f.leave and f.leave[r] <= self.round < f.back.get(r, 1 << 30))

    def send(self, msgs: list[Estimate]) -> None:
        for m in msgs:
            data = m.to_bytes()
            self.bytes_total += len(data)
            self.pose_sends += len(m.poses)
            if self.rng.random() < self.faults.drop:
                continue
            self.queue.append(data)
            if self.rng.random() < self.faults.duplicate:
                self.queue.append(data)

    def deliver(self) -> None:
        q, self.queue = self.queue, []
        if self.faults.reorder:
            self.rng.shuffle(q)
        for data in q:
            msg = Estimate.from_bytes(data)
            if msg.recipient in self.robots and self.present(msg.recipient):
                self.robots[msg.recipient].receive(msg)

    # ------------------------------------------------------------------------------------ rounds
    def start(self) -> None:
        """Round 0: every robot sends its initial estimate."""
        for r, rob in self.robots.items():
            self.send(rob.messages(scalars=False))
        self.deliver()
        self.record()

    def run_round(self) -> bool:
        """One round, colour by colour; True when the team is still (every present robot, two rounds)."""
        self.round += 1
        for c in sorted({p.colour for p in self.parts.values()}):
            for r, rob in self.robots.items():
                if self.parts[r].colour == c and self.present(r):
                    self.send(rob.step())
            self.deliver()
        self.record()
        still = all(rob.still for r, rob in self.robots.items() if self.present(r))
        self.still_rounds = self.still_rounds + 1 if still else 0
        return self.still_rounds >= 2

    def agree_mu0(self, barc: float) -> dict[int, float]:
        """GNC's initial mu: each robot proposes one from its own loops and relays the smallest it has heard with
        its estimates, as many times as there are robots, so that every robot of a group ends with the group's
        smallest (the centralised GNC's) even when the robot that proposed it is no neighbour of its own."""
        for rob in self.robots.values():
            rob.propose_mu0(barc)
        for _ in range(len(self.robots)):
            for rob in self.robots.values():
                self.send(rob.messages(scalars=True))
            self.deliver()
        return {r: rob.team_mu0() for r, rob in self.robots.items()}

    def record(self) -> None:
        self.history.append(self.cost())
        self.bytes_history.append(self.bytes_total)

    # ------------------------------------------------------------------------------------ the team's state
    def estimate(self):
        poses, scales, weights = {}, {}, {}
        for r, rob in self.robots.items():
            poses.update(rob.poses)
            for n in self.parts[r].owned:
                if n in rob.scales:
                    scales[n] = rob.scales[n]
                weights[n] = rob.weights.get(n, 1.0)
        if self.settings.formulation == "shared":
            keeper = self.robots[min(r for r in self.robots if self.present(r))]
            scales = {n: keeper.shared for n in scales}
        return poses, scales, weights

    def cost(self) -> float:
        """The team's objective at the robots' current estimate (the centralised problem's error)."""
        poses, scales, weights = self.estimate()
        return problem_error(self.problem, poses, scales, weights)


def problem_error(problem: Problem, poses, scales, weights) -> float:
    """The centralised problem's error at the team's estimate, with GNC weights `weights`."""
    values = problem_values(problem, poses, scales)
    err = problem.builtin_graph(weights).error(values)
    if problem.scale_loops is not None:
        err += _ScaleTerm(problem, weights).error(values)
    return float(err)


def problem_values(problem: Problem, poses, scales) -> gtsam.Values:
    """The team's estimate as the centralised problem's values."""
    values = pose_values({k: poses[k] for k in problem.graph.keys()}, problem.is_2d)
    sl = problem.scale_loops
    if sl is not None:
        for n, k in zip(sl.edge, sl.key_s):
            if not values.exists(int(k)):
                values.insert(int(k), float(scales[int(n)]))
    return values


def solve_distributed(graph: PoseGraph, settings: Settings | None = None, solver: str = "lm", *,
                      initial_poses=None, gt_scales=None, max_rounds: int = 300, faults: Faults | None = None,
                      probability: float = 0.99, mu_step: float = 1.4, gnc_rounds: int = 4,
                      max_gnc: int = 100, ls_rounds: int = 10, on_round=None,
                      stop_when_still: bool = True) -> DistributedResult:
    """Solve `graph` with simulated robots (module docstring); `solver` 'lm' (least squares) or 'gnc'.
    `stop_when_still=False` runs `max_rounds` rounds whatever (the fixed schedule of the robot processes). With
    `settings.gnc_plan` (solver 'gnc') the team runs the plan's rounds and the robots do GNC themselves
    (graph.distributed.gnc_plan); `max_rounds`, `mu_step`, `gnc_rounds`, `ls_rounds` and `max_gnc` then do not
    apply. GNC without a plan: `ls_rounds` rounds of least squares (all weights 1) before GNC's initial mu is taken
    from the residuals (they only need to tell the wrong loops' large residuals from the rest; on the outdoor
    6-robot graph 60 rounds of it sent 140 kB, half of what gathering the graph would, and still moved), then at most
    `gnc_rounds` rounds per step of mu, then the final weights' least squares to convergence (at most
    `max_rounds`)."""
    if solver not in ("lm", "gnc"):
        raise InputError(f"solver must be 'lm' or 'gnc', got {solver!r}")
    t0 = time.perf_counter()
    settings = settings or Settings()
    plan = settings.gnc_plan
    if plan is not None and solver != "gnc":
        raise InputError("a GNC plan (Settings.gnc_plan) runs with solver 'gnc'")
    team = Team(graph, settings, initial_poses=initial_poses, gt_scales=gt_scales, faults=faults)
    team.start()
    converged = False
    first = ls_rounds if solver == "gnc" else max_rounds
    for _ in range(plan.total if plan is not None else first):  # a plan: every decision the robots' own
        converged = team.run_round()
        if on_round:
            on_round(team)
        if converged and stop_when_still and plan is None:
            break
    k = plan.steps if plan is not None else 0
    if solver == "gnc" and plan is None:
        barc = inlier_threshold(probability, graph.is_2d)
        mu = team.agree_mu0(barc)
        if max(mu.values()) > 0:
            for k in range(1, max_gnc + 1):
                for r, rob in team.robots.items():
                    if team.present(r) and mu[r] > 0:
                        rob.gnc_update(mu[r], barc)
                team.still_rounds = 0
                for _ in range(gnc_rounds):
                    if team.run_round():
                        break
                if all(rob.binary() for r, rob in team.robots.items() if team.present(r)):
                    break
                mu = {r: m * mu_step for r, m in mu.items()}
        team.still_rounds = 0
        converged = False  # what it reports is the final weights' least squares, not the one before GNC
        for _ in range(max_rounds):  # the final weights' least squares, to convergence
            if converged := team.run_round():
                break
    poses, scales, weights = team.estimate()
    groups = [sorted({robot_of(x) for x in c}) for c in graph.components()]
    rejected = sorted(n for n, w in weights.items() if w < 0.5) if solver == "gnc" else []
    tls = None
    if solver == "gnc":
        barc = plan.barc if plan is not None else inlier_threshold(probability, graph.is_2d)
        tls = tls_objective(team.problem, problem_values(team.problem, poses, scales), barc)
    return DistributedResult(poses, scales, weights if solver == "gnc" else {}, rejected, team.round,
                             team.history, team.bytes_history, team.history[0], team.history[-1], team.bytes_total,
                             team.pose_sends, gather_bytes(graph), len(team.robots), groups, converged,
                             time.perf_counter() - t0, k, tls)


