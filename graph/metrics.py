"""Numbers to judge a pose-graph solution by: the SE-Sync objective and the absolute trajectory error."""

from __future__ import annotations

import numpy as np

from .init import isotropic_weights
from .pose_graph import PoseGraph


def se_sync_cost(graph: PoseGraph, poses: dict[int, np.ndarray]) -> float:
    """SE-Sync's objective F = sum kappa ||R_j - R_i Rt_ij||_F^2 + tau ||t_j - t_i - R_i tt_ij||^2 (the formula
    and kappa/tau of the SE-Sync data's PROVENANCE). Not GTSAM's error: compare with published SE-Sync optima."""
    total = 0.0
    for e in graph.edges:
        kappa, tau = isotropic_weights(e.info * e.confidence, graph.is_2d)
        Ti, Tj = poses[e.key_i], poses[e.key_j]
        Ri, Rj = Ti[:3, :3], Tj[:3, :3]
        total += kappa * np.sum((Rj - Ri @ e.T_ij[:3, :3]) ** 2)
        total += tau * np.sum((Tj[:3, 3] - Ti[:3, 3] - Ri @ e.T_ij[:3, 3]) ** 2)
    return float(total)


def ate(poses: dict[int, np.ndarray], gt: dict[int, np.ndarray]) -> tuple[float, float]:
    """Mean and std (m) of position errors over all keys of `gt` after one rigid alignment (Umeyama without
    scale) of all robots together, as evo's APE with --align."""
    keys = sorted(gt)
    X = np.stack([poses[k][:3, 3] for k in keys])
    Y = np.stack([gt[k][:3, 3] for k in keys])
    mx, my = X.mean(0), Y.mean(0)
    U, _, Vt = np.linalg.svd((Y - my).T @ (X - mx))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    err = np.linalg.norm((X - mx) @ R.T + my - Y, axis=1)
    return float(err.mean()), float(err.std())
