"""g2o pose-graph files: read VERTEX_SE3:QUAT / EDGE_SE3:QUAT (and 2D VERTEX_SE2 / EDGE_SE2), write the 3D kind.

Format (as SE-Sync, GTSAM's readG2o, Kimera-RPGO and DGS use it):
    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT i j x y z qx qy qz qw  I11 I12 ... I66   (21 upper-triangular entries, translation first)
    VERTEX_SE2 id x y theta
    EDGE_SE2 i j dx dy dtheta  I11 I12 I13 I22 I23 I33
Ids are GTSAM keys (Symbol keys for multi-robot files). The information matrix is reordered to GTSAM's
(rotation, translation) order on read and back on write. Consecutive keys of one robot are odometry, every other
edge a loop closure. An edge to a keyframe of a robot the file has no vertex of (DGS writes each robot's
inter-robot edges into its own file) is kept in `PoseGraph.pending` until the graphs are merged; an edge to a
missing vertex of the file's own robot is an error. A file without any VERTEX line (CSAIL.g2o) gets its poses
by composing edges along a spanning tree. Every malformed line raises InputError naming file:line; an
information matrix that is not positive definite is refused or replaced by the chosen policy (graph.information).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path, text_lines

from .information import POLICIES, apply_policy, is_positive_definite
from .pose_graph import LOOP, ODOMETRY, Edge, PoseGraph, check_information, is_odometry_pair, key_robot

_FIELDS = {"VERTEX_SE3:QUAT": 9, "EDGE_SE3:QUAT": 31, "VERTEX_SE2": 5, "EDGE_SE2": 12}
_IGNORED = {"FIX"}  # g2o's gauge hint; we anchor every connected component ourselves


def se2_matrix(x: float, y: float, theta: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = [x, y]
    return T


def read_g2o(path: str | Path, information: str = "strict") -> PoseGraph:
    """Parse a g2o file into a PoseGraph (see the module docstring for the accepted lines). `information` is
    the policy for matrices that are not positive definite (graph.information: strict, repair, isotropic);
    replaced edges keep the file's matrix in `Edge.info_raw` (count them with `repaired_edges`)."""
    if information not in POLICIES:
        raise InputError(f"information policy must be one of {', '.join(POLICIES)}, got {information!r}")
    path = Path(path)
    if not path.is_file():
        raise InputError(f"g2o file not found: {path}")
    graph = PoseGraph()
    edge_lines: list[tuple[str, int, list[str]]] = []
    vertex: dict[int, tuple[list[float], str]] = {}
    kinds = set()
    for lineno, line in text_lines(path, "g2o"):
        s = line.split("#", 1)[0].split()
        if not s:
            continue
        where = f"{path}:{lineno}"
        tag = s[0]
        if tag in _IGNORED:
            continue
        if tag not in _FIELDS:
            raise InputError(f"{where}: unknown g2o element {tag!r} (expected one of {', '.join(_FIELDS)})")
        if len(s) != _FIELDS[tag]:
            raise InputError(f"{where}: {tag} needs {_FIELDS[tag] - 1} values after the tag, got {len(s) - 1}")
        kinds.add("2d" if tag.endswith("SE2") else "3d")
        if len(kinds) > 1:
            raise InputError(f"{where}: file mixes SE2 and SE3 elements")
        if tag.startswith("VERTEX"):
            key = _parse_key(s[1], where)
            vals = _parse_floats(s[2:], where)
            if key in vertex:
                raise InputError(f"{where}: vertex {s[1]} defined twice")
            vertex[key] = (vals, where)
        else:
            edge_lines.append((tag, lineno, s))
    graph.is_2d = kinds == {"2d"}
    if vertex:
        keys = list(vertex)
        vals = np.array([vertex[k][0] for k in keys])
        if graph.is_2d:
            mats = [se2_matrix(*v) for v in vals]
        else:
            n = np.linalg.norm(vals[:, 3:7], axis=1)
            bad = np.flatnonzero((n < 0.5) | (n > 1.5))
            if len(bad):
                raise InputError(f"{vertex[keys[bad[0]]][1]}: quaternion (qx qy qz qw) has norm {n[bad[0]]:.3g}, "
                                 f"expected 1")
            mats = np.tile(np.eye(4), (len(keys), 1, 1))
            mats[:, :3, :3] = _quat_xyzw_to_matrix(vals[:, 3:7] / n[:, None])
            mats[:, :3, 3] = vals[:, :3]
        graph.poses = dict(zip(keys, mats))
    have_vertices = bool(graph.poses)
    if edge_lines:
        _add_edges(graph, path, edge_lines, have_vertices, information)
    if not graph.poses:
        raise InputError(f"{path}: no vertices or edges")
    if not have_vertices:
        from .init import spanning_tree_poses

        graph.poses = spanning_tree_poses(graph)
    return graph


def write_g2o(graph: PoseGraph, path: str | Path, poses: dict[int, np.ndarray] | None = None) -> Path:
    """Write `graph` (with `poses` in place of its own when given) as 3D g2o, atomically. Up-to-scale loop
    closures are written with their measured translation (scale information is not part of g2o). An edge whose
    matrix was replaced on reading (graph.information) is written with the file's matrix, as it came in."""
    poses = graph.poses if poses is None else poses
    p = [3, 4, 5, 0, 1, 2]
    iu = np.triu_indices(6)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            for k in sorted(graph.poses):
                T = np.asarray(poses[k])
                if not np.all(np.isfinite(T)):
                    raise InputError(f"write_g2o({path}): pose {k} is not finite")
                xyz, q = se3.to_tum(T)
                f.write(f"VERTEX_SE3:QUAT {k} " + " ".join(f"{v:.12g}" for v in (*xyz, *q)) + "\n")
            for e in graph.edges:
                xyz, q = se3.to_tum(e.T_ij)
                M = e.info if e.info_raw is None else e.info_raw  # the file's own matrix, as read
                info = (M * e.confidence)[np.ix_(p, p)][iu]
                f.write(f"EDGE_SE3:QUAT {e.key_i} {e.key_j} " + " ".join(f"{v:.12g}" for v in (*xyz, *q))
                        + " " + " ".join(f"{v:.12g}" for v in info) + "\n")
    return Path(path)


def repaired_edges(graph: PoseGraph) -> dict[str, int]:
    """How many edges had their information matrix replaced, per rule ("repair", "isotropic")."""
    out: dict[str, int] = {}
    for e in graph.edges + graph.pending:
        if e.info_policy:
            out[e.info_policy] = out.get(e.info_policy, 0) + 1
    return out


def _add_edges(graph: PoseGraph, path: Path, edge_lines: list, have_vertices: bool, policy: str) -> None:
    """Vectorised conversion and validation of all edge lines (a per-line NumPy path costs ~1 ms an edge)."""
    wheres = [f"{path}:{n}" for _, n, _ in edge_lines]
    ki = [_parse_key(s[1], w) for (_, _, s), w in zip(edge_lines, wheres)]
    kj = [_parse_key(s[2], w) for (_, _, s), w in zip(edge_lines, wheres)]
    vals = np.array([_parse_floats(s[3:], w) for (_, _, s), w in zip(edge_lines, wheres)])
    E = len(edge_lines)
    if graph.is_2d:
        c, s_ = np.cos(vals[:, 2]), np.sin(vals[:, 2])
        T = np.tile(np.eye(4), (E, 1, 1))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s_, s_, c
        T[:, :2, 3] = vals[:, :2]
        I3 = np.zeros((E, 3, 3))
        I3[:, np.triu_indices(3)[0], np.triu_indices(3)[1]] = vals[:, 3:]
        I3 = I3 + np.triu(I3, 1).swapaxes(1, 2)
        info = np.tile(np.eye(6), (E, 1, 1))
        idx = [3, 4, 2]
        info[:, np.array(idx)[:, None], np.array(idx)[None, :]] = I3
    else:
        q = vals[:, 3:7]
        n = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero((n < 0.5) | (n > 1.5))
        if len(bad):
            raise InputError(f"{wheres[bad[0]]}: quaternion (qx qy qz qw) has norm {n[bad[0]]:.3g}, expected 1")
        T = np.tile(np.eye(4), (E, 1, 1))
        T[:, :3, :3] = _quat_xyzw_to_matrix(q / n[:, None])
        T[:, :3, 3] = vals[:, :3]
        M = np.zeros((E, 6, 6))
        iu = np.triu_indices(6)
        M[:, iu[0], iu[1]] = vals[:, 7:]
        M = M + np.triu(M, 1).swapaxes(1, 2)
        p = np.array([3, 4, 5, 0, 1, 2])
        info = M[:, p[:, None], p[None, :]]
    raw: dict[int, tuple[np.ndarray, str]] = {}
    for b in np.flatnonzero(~is_positive_definite(info)):
        fixed = apply_policy(info[b], policy, graph.is_2d)
        if fixed is None:
            if policy != "strict":
                M = info[b][np.ix_([3, 4, 2], [3, 4, 2])] if graph.is_2d else info[b]
                raise InputError(f"{wheres[b]}: information matrix is not positive definite and cannot be "
                                 f"replaced under --information {policy}: no positive eigenvalue in a diagonal "
                                 f"block (eigenvalues {np.round(np.linalg.eigvalsh(M), 6).tolist()})")
            check_information(info[b], wheres[b])  # raises with the eigenvalues
            raise InputError(f"{wheres[b]}: information matrix is not positive definite")
        raw[int(b)] = (info[b].copy(), fixed[1])
        info[b] = fixed[0]
    own = {key_robot(k) for k in graph.poses}
    for e in range(E):
        if not have_vertices:
            graph.poses.setdefault(ki[e], np.eye(4))
            graph.poses.setdefault(kj[e], np.eye(4))
        if ki[e] == kj[e]:
            raise InputError(f"{wheres[e]}: edge from vertex {ki[e]} to itself")
        kind = ODOMETRY if is_odometry_pair(ki[e], kj[e]) else LOOP
        edge = Edge(ki[e], kj[e], T[e], info[e], kind, source=wheres[e])
        if e in raw:
            edge.info_raw, edge.info_policy = raw[e]
        missing = [k for k in (ki[e], kj[e]) if k not in graph.poses]
        if not missing:
            graph.edges.append(edge)
        elif all(key_robot(k) is not None and key_robot(k) not in own for k in missing):
            graph.pending.append(edge)  # to another robot's keyframe (DGS per-robot files): kept for merge
        else:
            raise InputError(f"{wheres[e]}: edge {ki[e]}-{kj[e]} refers to vertex {missing[0]}, which the file "
                             f"does not define")


def _quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def _parse_key(tok: str, where: str) -> int:
    try:
        k = int(tok)
    except ValueError:
        raise InputError(f"{where}: vertex id {tok!r} is not an integer") from None
    if k < 0 or k >= 1 << 64:
        raise InputError(f"{where}: vertex id {tok} out of range for a GTSAM key")
    return k


def _parse_floats(toks: list[str], where: str) -> list[float]:
    try:
        vals = [float(t) for t in toks]
    except ValueError as e:
        raise InputError(f"{where}: expected numbers ({e})") from None
    if not all(np.isfinite(vals)):
        raise InputError(f"{where}: NaN or Inf value")
    return vals
