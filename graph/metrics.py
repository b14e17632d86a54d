"""Numbers to judge a pose-graph solution by: the SE-Sync objective and the absolute trajectory error."""

from __future__ import annotations

import numpy as np

from .information import se_sync_weights
from .pose_graph import PoseGraph


def se_sync_cost(graph: PoseGraph, poses: dict[int, np.ndarray]) -> float:
    """SE-Sync's objective F = sum kappa ||R_j - R_i Rt_ij||_F^2 + tau ||t_j - t_i - R_i tt_ij||^2 (the formula
    and kappa/tau of the SE-Sync data's PROVENANCE; graph.information.se_sync_weights). Not GTSAM's error: compare
    with published SE-Sync optima."""
    if not graph.edges:
        return 0.0
    w = se_sync_weights(graph.edges, graph.is_2d)
    Ti = np.stack([poses[e.key_i] for e in graph.edges])
    Tj = np.stack([poses[e.key_j] for e in graph.edges])
    Tm = np.stack([e.T_ij for e in graph.edges])
    dR = Tj[:, :3, :3] - Ti[:, :3, :3] @ Tm[:, :3, :3]
    dt = Tj[:, :3, 3] - Ti[:, :3, 3] - np.einsum("eab,eb->ea", Ti[:, :3, :3], Tm[:, :3, 3])
    return float(np.sum(w[:, 0] * np.einsum("eab,eab->e", dR, dR)) + np.sum(w[:, 1] * np.einsum("ea,ea->e", dt, dt)))


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
