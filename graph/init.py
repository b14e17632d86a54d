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

`initialize` runs both GTSAM's initialiser (gtsam.InitializePose3; lago in 2D) and ours on every connected
component and keeps, per component, the one with the lower objective; ours where GTSAM's fails (an
indeterminate system, or lago's diagonal-noise requirement).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from swarmsplat.kernels.errors import GraphError, InputError

from .information import isotropic_weights, se_sync_weights  # noqa: F401 (isotropic_weights re-exported)
from .pose_graph import PoseGraph


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
    w = se_sync_weights(graph.edges, graph.is_2d)
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


# ------------------------------------------------------------------------------------------- choice per component
INIT_METHODS = ("best", "chordal", "gtsam", "file")


@dataclass
class InitReport:
    """What `initialize` did: per connected component its size, the candidates' objective values (None: the
    candidate failed, `gtsam_failure` says why) and the one kept."""

    method: str
    objective: str
    components: list[dict] = field(default_factory=list)
    time_s: float = 0.0

    def chosen(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self.components:
            out[c["chosen"]] = out.get(c["chosen"], 0) + 1
        return out


def initialize(graph: PoseGraph, method: str = "best", objective: str = "g2o") -> tuple[dict[int, np.ndarray],
                                                                                        InitReport]:
    """Initial poses for every key and a report. `method`: "chordal" (ours, `chordal_initialization`), "gtsam"
    (gtsam.InitializePose3 / lago per component, ours where it fails), "best" (both; per connected component the
    one with the lower `objective`, "g2o" or "se-sync" as in graph.formulations), "file" (the graph's poses).
    Each component's anchor (its smallest key) keeps its pose in every case."""
    if method not in INIT_METHODS:
        raise InputError(f"initialisation must be one of {INIT_METHODS}, got {method!r}")
    t0 = time.perf_counter()
    report = InitReport(method, objective)
    if method == "file":
        report.time_s = time.perf_counter() - t0
        return dict(graph.poses), report
    ours = chordal_initialization(graph) if method in ("best", "chordal") else None
    out = dict(graph.poses)
    by_comp: dict[int, list[int]] = {}
    comp_of = {}
    components = graph.components()
    for c in components:
        for k in c:
            comp_of[k] = c[0]
    for n, e in enumerate(graph.edges):
        by_comp.setdefault(comp_of[e.key_i], []).append(n)
    for comp in components:
        edges = by_comp.get(comp[0], [])
        entry = {"anchor": comp[0], "poses": len(comp), "edges": len(edges), "errors": {}, "gtsam_failure": None}
        cands: dict[str, dict[int, np.ndarray]] = {}
        between = _between_graph(graph, edges) if not graph.is_2d or objective == "g2o" else None
        if method in ("best", "gtsam") and edges:
            try:
                cands["gtsam"] = _gtsam_initialization(graph, comp, edges, between)
            except (RuntimeError, ValueError) as e:  # "Indeterminant linear system", lago's noise-model check
                entry["gtsam_failure"] = str(e).splitlines()[0][:200]
        if ours is not None or "gtsam" not in cands:
            if ours is None:
                ours = chordal_initialization(graph)
            cands["chordal"] = {k: ours[k] for k in comp}
        score = _component_objective(graph, edges, objective, between)
        for name, poses in cands.items():
            entry["errors"][name] = score(poses)
        best = min(cands, key=lambda m: (not np.isfinite(entry["errors"][m]), entry["errors"][m], m != "chordal"))
        entry["chosen"] = best
        out.update(cands[best])
        report.components.append(entry)
    report.time_s = time.perf_counter() - t0
    return out, report


def _between_graph(graph: PoseGraph, edges: list[int]) -> gtsam.NonlinearFactorGraph:
    """The g2o objective's factors (graph.formulations.between_factor) of the edges `edges`."""
    from .formulations import between_factor  # formulations does not import this module

    nfg = gtsam.NonlinearFactorGraph()
    for n in edges:
        e = graph.edges[n]
        nfg.add(between_factor(e.key_i, e.key_j, gtsam.Pose3(e.T_ij), e.info * e.confidence, graph.is_2d))
    return nfg


def _component_objective(graph: PoseGraph, edges: list[int], objective: str, between):
    """poses -> GTSAM's error (0.5 sum of squared whitened residuals) of the edges `edges` under `objective`
    (se-sync: 0.5 * SE-Sync's F, in NumPy; g2o: the factors `between`)."""
    from .formulations import pose_values
    from .metrics import se_sync_cost

    sub = PoseGraph({}, [graph.edges[n] for n in edges], graph.is_2d)
    keys = sorted({e.key_i for e in sub.edges} | {e.key_j for e in sub.edges})
    if objective == "se-sync":
        return lambda poses: 0.5 * se_sync_cost(sub, poses)
    return lambda poses: float(between.error(pose_values({k: poses[k] for k in keys}, graph.is_2d)))


def _gtsam_initialization(graph: PoseGraph, comp: list[int], edges: list[int], between) -> dict[int, np.ndarray]:
    """GTSAM's initialiser on one component, anchored at its first key's pose: InitializePose3.initialize
    (chordal rotations, then one Gauss-Newton step on the poses) on the factors `between` in 3D; lago.initialize
    in 2D (diagonal noise models where the information is diagonal: lago needs them). Raises GTSAM's
    RuntimeError / ValueError where it cannot (indeterminate system, non-diagonal noise in lago)."""
    anchor = graph.poses[comp[0]]
    if graph.is_2d:
        nfg = gtsam.NonlinearFactorGraph()
        for n in edges:
            e = graph.edges[n]
            sub = (e.info * e.confidence)[np.ix_([3, 4, 2], [3, 4, 2])]
            diagonal = np.count_nonzero(sub - np.diag(np.diag(sub))) == 0
            model = (gtsam.noiseModel.Diagonal.Precisions(np.diag(sub).copy()) if diagonal
                     else gtsam.noiseModel.Gaussian.Information(sub))
            nfg.add(gtsam.BetweenFactorPose2(e.key_i, e.key_j, _pose2(e.T_ij), model))
        nfg.add(gtsam.PriorFactorPose2(comp[0], _pose2(anchor), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        values = gtsam.lago.initialize(nfg)
        return {k: _se2(values.atPose2(k)) for k in comp}
    nfg = gtsam.NonlinearFactorGraph(between)
    nfg.add(gtsam.PriorFactorPose3(comp[0], gtsam.Pose3(anchor), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    values = gtsam.InitializePose3.initialize(nfg)
    X = gtsam.utilities.extractPose3(values)
    out = {}
    for k, row in zip(sorted(comp), X[_sorted_positions(values, comp)]):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = row[:9].reshape(3, 3), row[9:]
        out[k] = T
    return out


def _sorted_positions(values: gtsam.Values, comp: list[int]) -> np.ndarray:
    """Rows of extractPose3(values) (Values' key order) holding the sorted keys `comp`."""
    keys = np.array(values.keys(), dtype=np.uint64)
    order = np.argsort(keys)
    return order[np.searchsorted(keys[order], np.array(sorted(comp), dtype=np.uint64))]


def _pose2(T: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0]))


def _se2(p: gtsam.Pose2) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(p.theta()), np.sin(p.theta())
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = [p.x(), p.y()]
    return T
