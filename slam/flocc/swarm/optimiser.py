"""What the elected robot does with the graphs it gathered: build one multi-robot pose graph and solve it.

Robot r's keyframe i is GTSAM key `robot_key(robot_char(r), i)`. Odometry edges come from consecutive keyframe
poses of each robot's metric odometry; inter-robot loops (unit translation, confidence p, eq. 6 scale) come from
the submission of the lower-id robot of each pair, which is the robot that registered them (`node.py`). The
initial guess is deterministic (odometry, joined along loops scaled by eq. 6), so the same graphs give the same
estimate whichever process solves them. The global frame is the odometry frame of the group's lowest robot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.errors import InputError

from .messages import GraphSubmission


@dataclass
class SolveConfig:
    """formulation: base | is | ss | shared (graph.formulations); solver: lm | gnc on the elected robot, or
    distributed (every robot solves its own part, distributed.py; not through `solve_group`).
    uniform_noise: Swarm-SLAM-like baseline — every factor (odometry and loops) gets the same information and
    confidences are ignored. Sigmas in radians and metres."""

    formulation: str = "is"
    solver: str = "lm"
    uniform_noise: bool = False
    odo_sigma_rot: float = 0.01
    odo_sigma_trans: float = 0.02
    loop_sigma_rot: float = 0.05
    loop_sigma_trans: float = 0.1

    def info(self, loop: bool) -> np.ndarray:
        if self.uniform_noise or not loop:
            r, t = self.odo_sigma_rot, self.odo_sigma_trans
        else:
            r, t = self.loop_sigma_rot, self.loop_sigma_trans
        return np.diag([1 / r**2] * 3 + [1 / t**2] * 3)


def warm_up() -> None:
    """Import the solver stack now (GTSAM and friends take seconds to import): a robot process calls this before
    its first tick so that its first solve does not stall it past a rendezvous window."""
    import swarmsplat.graph.formulations  # noqa: F401
    import swarmsplat.graph.init  # noqa: F401
    import swarmsplat.graph.solvers  # noqa: F401


def robot_char(robot: int) -> str:
    """GTSAM Symbol character of robot id `robot` (0 -> 'a', ...)."""
    if not 0 <= robot < 26:
        raise InputError(f"robot id {robot} has no Symbol character (0..25 supported)")
    return chr(ord("a") + robot)


@dataclass
class GroupSolution:
    robots: list[int]
    counts: list[int]
    poses: np.ndarray  # [sum(counts), 4, 4] T_global_kf, robot after robot
    scales: np.ndarray  # [L] optimised loop scales (formulations with scale variables), else eq. 6 scales
    graph: object  # graph.pose_graph.PoseGraph that was solved
    n_loops: int
    time_s: float
    final_error: float = 0.0  # the solved problem's objective


def build_graph(subs: dict[int, GraphSubmission], cfg: SolveConfig):
    """PoseGraph of the robots in `subs` (robot id -> its latest submission)."""
    from swarmsplat.graph.pose_graph import PoseGraph, robot_key

    g = PoseGraph()
    robots = sorted(subs)
    counts = {r: len(subs[r].odometry) for r in robots}
    for r in robots:
        c, odo = robot_char(r), subs[r].odometry
        for i in range(len(odo)):
            g.add_pose(robot_key(c, i), odo[i])
        for i in range(len(odo) - 1):
            g.add_odometry(robot_key(c, i), robot_key(c, i + 1), np.linalg.inv(odo[i]) @ odo[i + 1], cfg.info(False))
    rows = []
    for a in robots:
        lb = subs[a].loops()
        for n in range(len(lb.query_robot)):
            qa, qi, mb, mj = (int(lb.query_robot[n]), int(lb.query_index[n]), int(lb.match_robot[n]),
                              int(lb.match_index[n]))
            # the registering (lower) robot's copy only; keyframes the other robot has not submitted yet wait
            if qa != a or mb not in subs or mb <= a or qi >= counts[a] or mj >= counts[mb]:
                continue
            rows.append((qa, qi, mb, mj, n, a))
    for qa, qi, mb, mj, n, a in sorted(rows):
        lb = subs[a]
        p = 1.0 if cfg.uniform_noise else float(lb.confidence[n])
        g.add_loop(robot_key(robot_char(qa), qi), robot_key(robot_char(mb), mj), lb.T_query_match[n],
                   cfg.info(True), up_to_scale=True, confidence=p, odom_scale=float(lb.odom_scale[n]))
    return g


def initial_poses(graph) -> dict[int, np.ndarray]:
    """Odometry joined along loops whose translation is scaled by eq. 6 (breadth-first from each anchor)."""
    from swarmsplat.graph.init import spanning_tree_poses
    from swarmsplat.graph.pose_graph import Edge, PoseGraph

    metric = PoseGraph(dict(graph.poses))
    for e in graph.edges:
        T = e.T_ij.copy()
        if e.up_to_scale:
            T[:3, 3] *= e.odom_scale or 1.0
        metric.edges.append(Edge(e.key_i, e.key_j, T, e.info, e.kind))
    return spanning_tree_poses(metric)


def solve_group(subs: dict[int, GraphSubmission], cfg: SolveConfig) -> GroupSolution:
    """Build, initialise and solve the group's graph (module docstring)."""
    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.pose_graph import robot_key
    from swarmsplat.graph.solvers import solve

    g = build_graph(subs, cfg)
    problem = build_problem(g, cfg.formulation, "odometry", initial_poses=initial_poses(g))
    res = solve(problem, cfg.solver)
    robots = sorted(subs)
    counts = [len(subs[r].odometry) for r in robots]
    poses = np.stack([res.poses[robot_key(robot_char(r), i)] for r, c in zip(robots, counts) for i in range(c)])
    loops = [n for n, e in enumerate(g.edges) if e.kind == "loop"]
    scales = np.array([res.scales.get(n, g.edges[n].odom_scale or 1.0) for n in loops], dtype=np.float64)
    return GroupSolution(robots, counts, poses, scales, g, len(loops), res.time_s, res.final_error)
