"""Initial estimates for graphs given without a good one: chordal relaxation, and edge composition along a tree.

Chordal initialisation (Carlone et al., ICRA 2015, "Initialization techniques for 3D SLAM"), done per connected
component so robots not yet linked to the others (or graphs on which GTSAM's `InitializePose3` stops with an
indeterminate system) still get a solution:
  1. rotations: every edge says R_j = R_i R_ij, linear in the matrix entries. Each row of R obeys the same
     equations, so one sparse weighted least-squares system (3 unknowns per pose) is solved for three right-hand
     sides, then each 3x3 estimate is projected onto SO(3) (SVD).
  2. translations: with rotations fixed, t_j - t_i = R_i t_ij is linear; one Laplacian system, three RHS.
Each component's anchor (its smallest key) keeps its current pose. Weights follow SE-Sync's isotropic
reduction of each edge's information (kappa for rotation, tau for translation).
"""

from __future__ import annotations

from collections import deque

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from kernels.errors import GraphError

from .pose_graph import PoseGraph


def isotropic_weights(info: np.ndarray, is_2d: bool = False) -> tuple[float, float]:
    """SE-Sync's (kappa, tau) from a 6x6 GTSAM-ordered information matrix (PROVENANCE of the SE-Sync data)."""
    if is_2d:
        tau = 2.0 / np.trace(np.linalg.inv(info[3:5, 3:5]))
        return float(info[2, 2]), float(tau)
    tau = 3.0 / np.trace(np.linalg.inv(info[3:, 3:]))
    kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(info[:3, :3])))
    return float(kappa), float(tau)


def spanning_tree_poses(graph: PoseGraph) -> dict[int, np.ndarray]:
    """Compose edges breadth-first from each component's anchor (odometry first, so the tree follows the
    trajectories). Poses not reached keep their value."""
    adj: dict[int, list[tuple[int, np.ndarray]]] = {k: [] for k in graph.poses}
    for e in sorted(graph.edges, key=lambda e: e.kind != "odometry"):
        adj[e.key_i].append((e.key_j, e.T_ij))
        adj[e.key_j].append((e.key_i, np.linalg.inv(e.T_ij)))
    poses = dict(graph.poses)
    seen = set()
    for anchor in graph.anchors():
        seen.add(anchor)
        queue = deque([anchor])
        while queue:
            k = queue.popleft()
            for n, T in adj[k]:
                if n not in seen:
                    seen.add(n)
                    poses[n] = poses[k] @ T
                    queue.append(n)
    return poses


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vt


def chordal_initialization(graph: PoseGraph) -> dict[int, np.ndarray]:
    """Chordal-relaxation initial poses for every key of `graph` (see the module docstring)."""
    keys = graph.keys()
    idx = {k: n for n, k in enumerate(keys)}
    N, E = len(keys), len(graph.edges)
    if E == 0:
        return dict(graph.poses)
    anchors = graph.anchors()
    fixed = np.zeros(N, bool)
    fixed[[idx[a] for a in anchors]] = True
    free = np.flatnonzero(~fixed)
    col = -np.ones(N, int)
    col[free] = np.arange(len(free))

    ii = np.array([idx[e.key_i] for e in graph.edges])
    jj = np.array([idx[e.key_j] for e in graph.edges])
    Rij = np.stack([e.T_ij[:3, :3] for e in graph.edges])
    tij = np.stack([e.T_ij[:3, 3] for e in graph.edges])
    w = np.array([isotropic_weights(e.info * e.confidence, graph.is_2d) for e in graph.edges])
    kappa, tau = np.sqrt(w[:, 0]), np.sqrt(w[:, 1])
    R0 = np.stack([graph.poses[k][:3, :3] for k in keys])
    t0 = np.stack([graph.poses[k][:3, 3] for k in keys])

    # --- rotations: for each row a, x_j^a - R_ij^T x_i^a = 0 (x^a: row a of R as a column), weighted by kappa.
    rows, cols, vals = [], [], []
    rhs = np.zeros((3 * E, 3))  # 3 equations per edge, 3 right-hand sides (rows a of R)
    for m in range(3):  # equation m of each edge: component m of x_j - R_ij^T x_i
        r = 3 * np.arange(E) + m
        _add(rows, cols, vals, rhs, r, jj, np.eye(3)[m][None, :].repeat(E, 0) * kappa[:, None], col, R0, fixed)
        _add(rows, cols, vals, rhs, r, ii, -np.swapaxes(Rij, 1, 2)[:, m, :] * kappa[:, None], col, R0, fixed)
    X = _solve_lsq(rows, cols, vals, rhs, 3 * E, 3 * len(free), "rotation")
    R = R0.copy()
    if len(free):
        Rf = X.reshape(len(free), 3, 3)  # [pose, component of x^a, a] -> R[a, component] = Rf[:, comp, a]
        R[free] = _project_so3(np.swapaxes(Rf, 1, 2))

    # --- translations: t_j - t_i = R_i t_ij, weighted by tau, three coordinates as three right-hand sides.
    d = np.einsum("eab,eb->ea", R[ii], tij) * tau[:, None]
    rows, cols, vals = [], [], []
    rhs = d.copy()
    r = np.arange(E)
    for nodes, sign in ((jj, 1.0), (ii, -1.0)):
        f = fixed[nodes]
        rows.append(r[~f]); cols.append(col[nodes[~f]]); vals.append(np.full((~f).sum(), sign) * tau[~f])
        rhs[f] -= sign * tau[f, None] * t0[nodes[f]]
    Tt = _solve_lsq([np.concatenate(rows)], [np.concatenate(cols)], [np.concatenate(vals)], rhs, E, len(free),
                    "translation", flat=True)
    t = t0.copy()
    if len(free):
        t[free] = Tt
    out = {}
    for n, k in enumerate(keys):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[n], t[n]
        out[k] = T
    return out


def _add(rows, cols, vals, rhs, r, nodes, coef, col, R0, fixed):
    """Add coef[e] . x_{nodes[e]}^a to equation r[e]; fixed nodes go to the right-hand side (for all a)."""
    f = fixed[nodes]
    for c in range(3):
        rows.append(r[~f]); cols.append(3 * col[nodes[~f]] + c); vals.append(coef[~f, c])
    if f.any():
        # x^a of a fixed node is row a of its rotation: component c of x^a = R0[node, a, c]
        rhs[r[f]] -= np.einsum("ec,eac->ea", coef[f], R0[nodes[f]])


def _solve_lsq(rows, cols, vals, rhs, n_rows, n_cols, what, flat=False):
    if n_cols == 0:
        return np.zeros((0, 3))
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, n_cols))
    H = (A.T @ A).tocsc()
    b = A.T @ rhs
    try:
        lu = spla.splu(H, permc_spec="COLAMD")
        x = lu.solve(b)
    except RuntimeError as e:  # singular: a pose no edge reaches
        raise GraphError(f"chordal initialisation: the {what} system is singular ({e}); every pose needs an edge")
    if not np.all(np.isfinite(x)):
        raise GraphError(f"chordal initialisation: the {what} system has no finite solution")
    return x
