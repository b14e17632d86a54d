"""Build an optimisation problem from a PoseGraph in one of FLOCC-SLAM's formulations (§III-C).

  base   eq. 5: every loop is a BetweenFactorPose3; an up-to-scale loop's translation is multiplied by its
         initial scale (eq. 6's odometry ratio, the raw network scale 1, or ground truth) and then fixed.
  is     one scale variable per up-to-scale loop (eqs. 7-8), started at that initial scale.
  ss     IS plus smoothing: loops between the same two robots whose keyframes are fewer than `cluster_gap`
         apart on both robots form a cluster; consecutive members are tied by ||s_b - s_a||² / sigma_s².
  shared one scale variable for all up-to-scale loops.

Objectives: "g2o" (default) is the maximum-likelihood cost GTSAM and g2o minimise, one BetweenFactorPose3 (Pose2
for SE2 graphs) per edge with its full information matrix; "se-sync" is SE-Sync's chordal cost (graph.metrics.
se_sync_cost), one FrobeniusBetweenFactorPose3 (Pose2) per edge weighted by the edge's isotropic (kappa, tau):
GTSAM's error is then exactly 0.5 * F (plus the anchors), so its minimum is SE-Sync's published optimum. The
se-sync objective is for graphs without scale variables (base formulation, or no up-to-scale loops).

Metric loops (RGB-D, LiDAR) and odometry are BetweenFactorPose3 in every formulation. Each connected component
is anchored by a prior on its smallest key, so robots not yet linked keep their own frame. Every information
matrix is multiplied by the edge's confidence p (eq. 3). Scale variables get a weak prior (sigma 10 by
default, negligible against any loop) only so that a loop with ~zero translation cannot make the system
singular; `graph.solvers` keeps them positive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from swarmsplat.kernels.errors import InputError

from .information import diagonal_weights, se_sync_information, se_sync_weights
from .pose_graph import PoseGraph, key_index, key_robot

FORMULATIONS = ("base", "is", "ss", "shared")
OBJECTIVES = ("g2o", "se-sync")
SCALE_INITS = ("raw", "odometry", "gt")
SCALE_KEY_CHAR = 0xFE  # Symbol character of scale variables (not a printable robot name)
ANCHOR_SIGMA = 1e-6


def scale_key(n: int) -> int:
    return (SCALE_KEY_CHAR << 56) | n


@dataclass
class ScaleLoops:
    """Up-to-scale loops evaluated in NumPy (see graph.scale_factors.is_residuals). L loops."""

    edge: np.ndarray  # [L] index into PoseGraph.edges
    key_i: np.ndarray  # [L] uint64
    key_j: np.ndarray  # [L]
    key_s: np.ndarray  # [L] scale variable of each loop (one key for all loops in "shared")
    R_meas: np.ndarray  # [L, 3, 3]
    t_meas: np.ndarray  # [L, 3] network unit
    sqrt_info: np.ndarray  # [L, 6, 6] upper-triangular R with R^T R = p * info (network: in network units)
    residual: str = "metric"  # "metric" (eq. 8, the paper) or "network" (scale_factors.is_residuals_network)


@dataclass
class LoopFactor:
    """A built-in loop factor GNC may reweight: its edge and what is needed to rebuild it with another weight."""

    edge: int
    key_i: int
    key_j: int
    measured: gtsam.Pose3
    info: np.ndarray  # [6, 6] (already p-weighted)


@dataclass
class Problem:
    graph: PoseGraph
    formulation: str
    fixed: gtsam.NonlinearFactorGraph  # odometry, anchors, scale priors and smoothing: never reweighted
    loops: list[LoopFactor]  # built-in loop factors (metric loops, base-formulation loops)
    scale_loops: ScaleLoops | None  # up-to-scale loops with scale variables (is / ss / shared)
    initial: gtsam.Values
    scale_keys: list[int] = field(default_factory=list)
    clusters: list[list[int]] = field(default_factory=list)  # SS: edge indices per cluster
    is_2d: bool = False
    objective: str = "g2o"  # OBJECTIVES

    def builtin_graph(self, weights: dict[int, float] | None = None) -> gtsam.NonlinearFactorGraph:
        """fixed + built-in loops, each loop's information times weights[edge] (absent: 1; 0: left out)."""
        g = gtsam.NonlinearFactorGraph(self.fixed)
        for lf in self.loops:
            w = 1.0 if weights is None else weights.get(lf.edge, 1.0)
            if w > 0:
                g.add(between_factor(lf.key_i, lf.key_j, lf.measured, w * lf.info, self.is_2d, self.objective))
        return g


def between_factor(ki: int, kj: int, measured: gtsam.Pose3, info: np.ndarray, is_2d: bool, objective: str = "g2o"):
    """BetweenFactorPose3 (or Pose2 for 2D graphs) with a Gaussian noise model of information `info` [6, 6];
    for objective "se-sync" the FrobeniusBetweenFactor weighted by the (kappa, tau) of `info`, which is then
    the diagonal matrix `graph.information.se_sync_information` makes (times a GNC weight)."""
    if objective == "se-sync":
        return frobenius_factor(ki, kj, measured, *diagonal_weights(info, is_2d), is_2d)
    if is_2d:
        idx = [3, 4, 2]
        return gtsam.BetweenFactorPose2(ki, kj, _pose2(measured.matrix()),
                                        gtsam.noiseModel.Gaussian.Information(info[np.ix_(idx, idx)]))
    return gtsam.BetweenFactorPose3(ki, kj, measured, gtsam.noiseModel.Gaussian.Information(info))


def frobenius_factor(ki: int, kj: int, measured: gtsam.Pose3, kappa: float, tau: float, is_2d: bool):
    """GTSAM factor with error 0.5 (kappa ||R_j - R_i R_ij||_F^2 + tau ||t_j - t_i - R_i t_ij||^2): the
    FrobeniusBetweenFactor's residual is vec(T_i T_ij - T_j) (column-major, homogeneous row included, always 0
    there: weight 1)."""
    if is_2d:
        prec = np.array([kappa, kappa, 1.0, kappa, kappa, 1.0, tau, tau, 1.0])
        return gtsam.FrobeniusBetweenFactorPose2(ki, kj, _pose2(measured.matrix()),
                                                 gtsam.noiseModel.Diagonal.Precisions(prec))
    prec = np.array([kappa, kappa, kappa, 1.0] * 3 + [tau, tau, tau, 1.0])
    return gtsam.FrobeniusBetweenFactorPose3(ki, kj, measured, gtsam.noiseModel.Diagonal.Precisions(prec))


def pose_values(poses: dict[int, np.ndarray], is_2d: bool = False) -> gtsam.Values:
    """gtsam.Values of Pose3 (Pose2 for 2D graphs) from key -> 4x4 T_world_kf."""
    values = gtsam.Values()
    for k in sorted(poses):
        values.insert(k, _pose2(poses[k]) if is_2d else gtsam.Pose3(poses[k]))
    return values


def _pose2(T: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0]))


def initial_scales(graph: PoseGraph, scale_init: str, gt_scales: dict[int, float] | None = None) -> dict[int, float]:
    """Initial scale of each up-to-scale loop (edge index -> scale): 'raw' 1 (network unit as is), 'odometry'
    eq. 6's ratio stored on the edge (1 where the front-end gave none), 'gt' from `gt_scales`."""
    if scale_init not in SCALE_INITS:
        raise InputError(f"scale_init must be one of {SCALE_INITS}, got {scale_init!r}")
    out = {}
    for n, e in enumerate(graph.edges):
        if not e.up_to_scale:
            continue
        if scale_init == "raw":
            out[n] = 1.0
        elif scale_init == "odometry":
            out[n] = float(e.odom_scale) if e.odom_scale and e.odom_scale > 0 else 1.0
        else:
            if gt_scales is None or n not in gt_scales:
                raise InputError(f"scale_init='gt' needs a ground-truth scale for loop edge {n}")
            out[n] = float(gt_scales[n])
    return out


def scale_clusters(graph: PoseGraph, edges: list[int], gap: int = 10) -> list[list[int]]:
    """SS clusters: loops between the same two robots whose keyframe indices differ by < `gap` on both robots,
    chained (single linkage), each cluster ordered by keyframe index on the first robot."""
    by_pair: dict[tuple, list[tuple[int, int, int]]] = {}
    for n in edges:
        e = graph.edges[n]
        ri, rj = key_robot(e.key_i), key_robot(e.key_j)
        a, b = key_index(e.key_i), key_index(e.key_j)
        if (ri or "") > (rj or ""):
            ri, rj, a, b = rj, ri, b, a
        by_pair.setdefault((ri, rj), []).append((a, b, n))
    clusters = []
    for members in by_pair.values():
        members.sort()
        parent = list(range(len(members)))

        def find(x):
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for x in range(len(members)):
            for y in range(x + 1, len(members)):
                if members[y][0] - members[x][0] >= gap:
                    break
                if abs(members[y][1] - members[x][1]) < gap:
                    parent[find(y)] = find(x)
        groups: dict[int, list[int]] = {}
        for x, m in enumerate(members):
            groups.setdefault(find(x), []).append(m[2])
        clusters.extend(g for g in groups.values())
    return sorted(clusters, key=lambda c: c[0])


def build_problem(graph: PoseGraph, formulation: str = "base", scale_init: str = "odometry", *,
                  initial_poses: dict[int, np.ndarray] | None = None, gt_scales: dict[int, float] | None = None,
                  cluster_gap: int = 10, scale_sigma: float = 0.05, scale_prior_sigma: float = 10.0,
                  scale_residual: str = "metric", objective: str = "g2o",
                  anchors: list[int] | None = None) -> Problem:
    """Factor graph + initial values for `formulation` (module docstring). `initial_poses` defaults to the
    graph's own poses; `scale_sigma` is SS's 1/sqrt(Omega_s). `scale_residual`: "metric" is eq. 8 as the paper
    writes it; "network" compares in the network's unit (unbiased scales, see graph.scale_factors), with the
    translation information scaled by the initial scale squared. `objective`: "g2o" or "se-sync" (module
    docstring). `anchors`: the keys held fixed (default: the smallest key of each connected component)."""
    if objective not in OBJECTIVES:
        raise InputError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    if scale_residual not in ("metric", "network"):
        raise InputError(f"scale_residual must be 'metric' or 'network', got {scale_residual!r}")
    if formulation not in FORMULATIONS:
        raise InputError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
    is_2d = graph.is_2d
    if is_2d and any(e.up_to_scale for e in graph.edges):
        raise InputError("up-to-scale loop closures need a 3D graph")
    if objective == "se-sync" and formulation != "base" and any(e.up_to_scale for e in graph.edges):
        raise InputError(f"the se-sync objective has no scale variables: use formulation 'base', not {formulation!r}")
    poses = graph.poses if initial_poses is None else initial_poses
    s0 = initial_scales(graph, scale_init, gt_scales)
    fixed = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in graph.keys():
        values.insert(k, _pose2(poses[k]) if is_2d else gtsam.Pose3(poses[k]))
    for a in (graph.anchors() if anchors is None else anchors):
        if is_2d:
            fixed.add(gtsam.PriorFactorPose2(a, _pose2(poses[a]), gtsam.noiseModel.Isotropic.Sigma(3, ANCHOR_SIGMA)))
        else:
            fixed.add(gtsam.PriorFactorPose3(a, gtsam.Pose3(poses[a]),
                                             gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)))
    loops: list[LoopFactor] = []
    scaled: list[int] = []
    W = se_sync_weights(graph.edges, is_2d) if objective == "se-sync" else None
    for n, e in enumerate(graph.edges):
        info = se_sync_information(*W[n], is_2d) if W is not None else e.info * e.confidence
        if e.kind == "odometry":
            fixed.add(between_factor(e.key_i, e.key_j, gtsam.Pose3(e.T_ij), info, is_2d, objective))
        elif e.up_to_scale and formulation != "base":
            scaled.append(n)
        else:
            T = e.T_ij.copy()
            if e.up_to_scale:
                T[:3, 3] *= s0[n]
            loops.append(LoopFactor(n, e.key_i, e.key_j, gtsam.Pose3(T), info))
    problem = Problem(graph, formulation, fixed, loops, None, values, is_2d=is_2d, objective=objective)
    if not scaled:
        return problem

    # scale variables
    if formulation == "shared":
        key_of = {n: scale_key(0) for n in scaled}
        values.insert(scale_key(0), float(np.median([s0[n] for n in scaled])))
    else:
        key_of = {n: scale_key(m) for m, n in enumerate(scaled)}
        for n in scaled:
            values.insert(key_of[n], float(s0[n]))
    problem.scale_keys = sorted(set(key_of.values()))
    for k in problem.scale_keys:
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(1, scale_prior_sigma)
        fixed.add(gtsam.PriorFactorDouble(k, values.atDouble(k), prior_noise))
    if formulation == "ss":
        problem.clusters = scale_clusters(graph, scaled, cluster_gap)
        for c in problem.clusters:
            for a, b in zip(c[:-1], c[1:]):
                fixed.add(gtsam.BetweenFactorDouble(key_of[a], key_of[b], 0.0,
                                                    gtsam.noiseModel.Isotropic.Sigma(1, scale_sigma)))
    E = [graph.edges[n] for n in scaled]
    info = np.stack([e.info * e.confidence for e in E])
    if scale_residual == "network":
        S = np.ones((len(E), 6))
        S[:, 3:] = np.array([s0[n] for n in scaled])[:, None]
        info = S[:, :, None] * info * S[:, None, :]
    problem.scale_loops = ScaleLoops(
        edge=np.array(scaled),
        key_i=np.array([e.key_i for e in E], dtype=np.uint64),
        key_j=np.array([e.key_j for e in E], dtype=np.uint64),
        key_s=np.array([key_of[n] for n in scaled], dtype=np.uint64),
        R_meas=np.stack([e.T_ij[:3, :3] for e in E]),
        t_meas=np.stack([e.T_ij[:3, 3] for e in E]),
        sqrt_info=np.swapaxes(np.linalg.cholesky(info), 1, 2),
        residual=scale_residual,
    )
    return problem
