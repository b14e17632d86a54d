"""Synthetic multi-robot teams with monocular (up-to-scale) inter-robot loop closures, for FLOCC's experiment.

Robots drive random routes on a shared street grid (so they revisit each other's places), keyframes every
`kf_spacing` metres, gentle terrain. Odometry: per-step Gaussian noise plus a per-robot yaw-rate bias and scale
error (a LIO/VIO-like drift: tens of metres after half a kilometre). Inter-robot loops: `target_loops` pairs
drawn from all keyframe pairs of two robots closer than `loop_radius` with a similar heading. A loop's
measurement is what MASt3R would give:
rotation with ~1 deg noise, translation with noise, in the network's own unit — the true translation divided by
a scale that is correlated in space (log-normal per `scale_cell` x `scale_cell` cell, like one image domain)
with a small per-loop jitter. The eq. 6 scale the front-end would compute (odometry-pair translation over the
network's odometry-pair translation) is the loop's scale times the robot's odometry scale error times an
independent log-normal error. A few loops are
outliers (perceptual aliasing: a wrong pose), and correspondence ratios (eq. 1) are drawn lower for them; the
confidence p (eq. 2) follows from the ratio.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from . import lie
from .confidence import loop_confidence
from .metrics import ate  # noqa: F401  (re-exported: the experiment's metric)
from .pose_graph import PoseGraph, robot_key


@dataclass
class TeamConfig:
    robots: int = 6
    length_m: float = 583.0  # per robot: 6 x 583 m = 3.5 km
    kf_spacing: float = 1.0
    grid_step: float = 50.0
    grid_nodes: int = 5
    target_loops: int = 2000
    loop_radius: float = 10.0  # keyframes closer than this (m) can form a loop (the paper's pairs: < 10 m)
    loop_min_dist: float = 1.0
    odo_sigma_rot: float = 0.003  # rad per step
    odo_sigma_trans: float = 0.02  # m per step
    odo_yaw_bias: float = 0.0008  # rad per step, per robot sign/size random in [-1, 1] x this
    odo_scale_error: float = 0.01  # per-robot odometry scale error, std
    loop_sigma_rot: float = 0.02  # rad
    loop_sigma_trans: float = 0.15  # m, isotropic, before the unknown scale
    scale_log_sigma: float = 0.3  # spread of the network's scale between cells
    scale_jitter: float = 0.05  # per-loop log-scale jitter within a cell
    scale_cell: float = 40.0  # m
    odom_scale_log_sigma: float = 0.15  # eq. 6 estimate error (log)
    outlier_fraction: float = 0.02
    k: float = 5.0  # eq. 2 steepness
    seed: int = 0


@dataclass
class Team:
    graph: PoseGraph  # odometry-integrated poses (each robot in its own start frame) + edges
    gt: dict[int, np.ndarray]  # key -> true T_world_kf
    gt_scales: dict[int, float]  # loop edge index -> true scale (metric / network unit)
    outliers: set[int] = field(default_factory=set)  # loop edge indices that are outliers


def _route(rng: np.random.Generator, cfg: TeamConfig) -> np.ndarray:
    """Positions [N, 3] every kf_spacing metres along a random walk on the street grid."""
    n = cfg.grid_nodes
    node = np.array(rng.integers(0, n, 2))
    prev = None
    pts = []
    total = 0.0
    while total < cfg.length_m + cfg.grid_step:
        moves = [d for d in ((1, 0), (-1, 0), (0, 1), (0, -1)) if 0 <= node[0] + d[0] < n and 0 <= node[1] + d[1] < n]
        if prev is not None and len(moves) > 1:
            moves = [d for d in moves if (d[0], d[1]) != (-prev[0], -prev[1])]
        d = moves[rng.integers(len(moves))]
        a, b = node * cfg.grid_step, (node + d) * cfg.grid_step
        for t in np.arange(0.0, cfg.grid_step, 0.25):
            pts.append(a + (b - a) * t / cfg.grid_step)
        node, prev = node + np.array(d), d
        total += cfg.grid_step
    P = np.array(pts, dtype=float)
    # round corners (moving average over ~6 m) and resample by arc length
    k = 24
    P = np.array([P[max(0, i - k):i + k + 1].mean(0) for i in range(len(P))])
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    q = np.arange(0.0, min(cfg.length_m, s[-1]), cfg.kf_spacing)
    xy = np.stack([np.interp(q, s, P[:, 0]), np.interp(q, s, P[:, 1])], 1)
    lane = rng.uniform(-1.5, 1.5)
    z = 2.0 * np.sin(xy[:, 0] / 70.0) + 1.5 * np.cos(xy[:, 1] / 55.0)
    return np.column_stack([xy, z]), lane


def _poses_along(P: np.ndarray, lane: float) -> np.ndarray:
    d = np.gradient(P, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    left = np.stack([-d[:, 1], d[:, 0], np.zeros(len(d))], 1)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    up = np.cross(d, left)
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = d, left, up
    T[:, :3, 3] = P + lane * left
    return T


def make_team(cfg: TeamConfig | None = None) -> Team:
    """A synthetic team as described in the module docstring (deterministic for a given cfg.seed)."""
    cfg = cfg or TeamConfig()
    rng = np.random.default_rng(cfg.seed)
    names = [chr(ord("a") + r) for r in range(cfg.robots)]
    gt_T = {}
    graph = PoseGraph()
    odo_info = np.diag([1 / cfg.odo_sigma_rot**2] * 3 + [1 / cfg.odo_sigma_trans**2] * 3)
    odo_scale = {}
    for name in names:
        P, lane = _route(rng, cfg)
        T = _poses_along(P, lane)
        bias = rng.uniform(-1, 1) * cfg.odo_yaw_bias
        scale = 1.0 + rng.normal() * cfg.odo_scale_error
        odo_scale[name] = scale
        est = np.eye(4)
        for i in range(len(T)):
            gt_T[robot_key(name, i)] = T[i]
            graph.add_pose(robot_key(name, i), est)
            if i + 1 < len(T):
                rel = lie.between(T[i][None], T[i + 1][None])[0]
                noise = np.concatenate([rng.normal(size=3) * cfg.odo_sigma_rot + [0, 0, bias],
                                        rng.normal(size=3) * cfg.odo_sigma_trans])
                meas = rel @ lie.exp(noise[None])[0]
                meas[:3, 3] *= scale
                est = est @ meas
                graph.poses[robot_key(name, i + 1)] = est
                graph.add_odometry(robot_key(name, i), robot_key(name, i + 1), meas, odo_info)

    # loop candidates: nearest keyframe on each other robot, close and looking the same way
    keys = {n: [k for k in sorted(gt_T) if chr(k >> 56) == n] for n in names}
    pos = {n: np.stack([gt_T[k][:3, 3] for k in keys[n]]) for n in names}
    fwd = {n: np.stack([gt_T[k][:3, 0] for k in keys[n]]) for n in names}
    cands = []
    for ra in range(len(names)):
        for rb in range(ra + 1, len(names)):
            a, b = names[ra], names[rb]
            tree = cKDTree(pos[b])
            for i, js in enumerate(tree.query_ball_point(pos[a], cfg.loop_radius)):
                for j in js:
                    if (fwd[a][i] @ fwd[b][j] > np.cos(np.radians(45))
                            and np.linalg.norm(pos[a][i] - pos[b][j]) > cfg.loop_min_dist):
                        cands.append((keys[a][i], keys[b][j]))
    order = rng.permutation(len(cands))[: cfg.target_loops]
    cands = sorted(cands[n] for n in order)

    cells: dict[tuple, float] = {}
    loop_info = np.diag([1 / cfg.loop_sigma_rot**2] * 3 + [1 / cfg.loop_sigma_trans**2] * 3)
    team = Team(graph, gt_T, {})
    for ki, kj in cands:
        rel = lie.between(gt_T[ki][None], gt_T[kj][None])[0]
        c = tuple(np.floor(gt_T[ki][:2, 3] / cfg.scale_cell).astype(int))
        if c not in cells:
            cells[c] = float(np.exp(rng.normal() * cfg.scale_log_sigma))
        s_true = cells[c] * float(np.exp(rng.normal() * cfg.scale_jitter))  # metric = s_true * network unit
        outlier = rng.random() < cfg.outlier_fraction
        if outlier:
            R = lie.so3_exp((rng.normal(size=3) * 1.0)[None])[0]
            meas = rel.copy()
            meas[:3, :3] = rel[:3, :3] @ R
            meas[:3, 3] = rel[:3, 3] + rng.normal(size=3) * 5.0
            ratio = rng.uniform(0.3, 0.8)
        else:
            meas = rel.copy()
            meas[:3, :3] = rel[:3, :3] @ lie.so3_exp((rng.normal(size=3) * cfg.loop_sigma_rot)[None])[0]
            meas[:3, 3] = rel[:3, 3] + rng.normal(size=3) * cfg.loop_sigma_trans
            ratio = rng.uniform(0.4, 1.6)
        meas[:3, 3] /= s_true
        p = loop_confidence(ratio, k=cfg.k)
        # eq. 6 divides robot a's metric odometry (with that robot's scale error) by the network's odometry-pair
        # translation (a different image pair: its scale agrees with the loop's only up to the log-normal error)
        odom_scale = s_true * odo_scale[chr(ki >> 56)] * float(np.exp(rng.normal() * cfg.odom_scale_log_sigma))
        graph.add_loop(ki, kj, meas, loop_info, up_to_scale=True, confidence=p, odom_scale=odom_scale)
        n = len(graph.edges) - 1
        team.gt_scales[n] = s_true
        if outlier:
            team.outliers.add(n)
    return team
