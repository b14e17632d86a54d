"""The multi-robot pose graph as plain data: keyframe poses per robot, odometry, intra/inter-robot loop closures.

Keys are GTSAM keys. A robot's keyframe `i` is `gtsam.Symbol(robot_char, i).key()` (as Kimera-RPGO, DGS and
Swarm-SLAM write them); a single-robot graph read from a file with plain integer ids keeps them as keys (robot
None). Poses are `T_world_kf` 4x4 float64 matrices; an edge's `T_ij` is the pose of keyframe j in keyframe i's
frame (`T_world_i^-1 @ T_world_j`), its `info` a 6x6 information matrix in GTSAM's order (rotation, translation).

A loop closure may be known only up to scale (`up_to_scale=True`, monocular registration): its translation is in
the network's unit, optionally with the odometry-derived scale of eq. 6 (`odom_scale`), and its confidence `p`
(eq. 2) multiplies its information when the graph is built (`graph.confidence`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels.errors import InputError

ODOMETRY = "odometry"
LOOP = "loop"


def robot_key(robot: str, index: int) -> int:
    """GTSAM Symbol key of robot `robot` (one character) keyframe `index`: (ord(c) << 56) | index."""
    if len(robot) != 1:
        raise InputError(f"robot name must be one character (a GTSAM Symbol), got {robot!r}")
    if not 0 <= index < (1 << 56):
        raise InputError(f"keyframe index out of range: {index}")
    return (ord(robot) << 56) | int(index)


def key_robot(key: int) -> str | None:
    """Robot character of a Symbol key, None for a plain integer id (< 2^56)."""
    c = key >> 56
    return chr(c) if c else None


def key_index(key: int) -> int:
    return key & ((1 << 56) - 1)


def key_str(key: int) -> str:
    r = key_robot(key)
    return f"{r}{key_index(key)}" if r else str(key)


@dataclass
class Edge:
    """One relative-pose measurement between keys i and j (T_ij = T_i^-1 T_j) with 6x6 information."""

    key_i: int
    key_j: int
    T_ij: np.ndarray  # [4, 4]
    info: np.ndarray  # [6, 6], rotation first
    kind: str = LOOP  # ODOMETRY or LOOP
    up_to_scale: bool = False  # translation known only up to scale (monocular registration)
    confidence: float = 1.0  # p of eq. 2; the built factor's information is p * info
    odom_scale: float | None = None  # eq. 6 scale: |t_odom metric| / |t_odom network|, for up_to_scale loops
    source: str = ""  # "file:line" the edge came from, for messages
    info_raw: np.ndarray | None = None  # the file's matrix where `info` replaced a non-positive-definite one
    info_policy: str = ""  # "" (as read), "repair" or "isotropic": the graph.information rule that made `info`

    @property
    def inter_robot(self) -> bool:
        return key_robot(self.key_i) != key_robot(self.key_j)


@dataclass
class PoseGraph:
    """Poses and edges of one or more robots. `is_2d` marks graphs read from SE2 files (z = roll = pitch = 0)."""

    poses: dict[int, np.ndarray] = field(default_factory=dict)  # key -> T_world_kf [4, 4]
    edges: list[Edge] = field(default_factory=list)
    is_2d: bool = False
    pending: list[Edge] = field(default_factory=list)  # edges to poses of robots not (yet) in this graph

    # ----------------------------------------------------------------------------------------- building
    def add_pose(self, key: int, T_world_kf: np.ndarray | None = None) -> int:
        T = np.eye(4) if T_world_kf is None else np.asarray(T_world_kf, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(f"pose {key_str(key)}: expected a finite 4x4 matrix")
        self.poses[int(key)] = T
        return int(key)

    def add_edge(self, edge: Edge, *, checked: bool = False) -> Edge:
        """Add `edge` after checking it (its keys are poses of the graph and differ, its information is positive
        definite, its confidence in (0, 1]). `checked`: an edge that passed the checks when added to another graph
        with these poses; its keys alone are checked again."""
        for k in (edge.key_i, edge.key_j):
            if k not in self.poses:
                where = f"{edge.source}: " if edge.source else ""
                raise InputError(f"{where}edge {key_str(edge.key_i)}-{key_str(edge.key_j)} refers to pose "
                                 f"{key_str(k)}, which the graph does not have")
        if checked:
            self.edges.append(edge)
            return edge
        if edge.key_i == edge.key_j:
            raise InputError(f"{edge.source or 'edge'}: self-loop on {key_str(edge.key_i)}")
        check_information(edge.info, edge.source or f"edge {key_str(edge.key_i)}-{key_str(edge.key_j)}")
        if not (0.0 < edge.confidence <= 1.0):
            raise InputError(f"{edge.source or 'edge'}: confidence must be in (0, 1], got {edge.confidence}")
        self.edges.append(edge)
        return edge

    def add_odometry(self, key_i: int, key_j: int, T_ij: np.ndarray, info: np.ndarray, source: str = "") -> Edge:
        return self.add_edge(Edge(key_i, key_j, np.asarray(T_ij, float), np.asarray(info, float), ODOMETRY,
                                  source=source))

    def add_loop(self, key_i: int, key_j: int, T_ij: np.ndarray, info: np.ndarray, *, up_to_scale: bool = False,
                 confidence: float = 1.0, odom_scale: float | None = None, source: str = "") -> Edge:
        return self.add_edge(Edge(key_i, key_j, np.asarray(T_ij, float), np.asarray(info, float), LOOP,
                                  up_to_scale, float(confidence), odom_scale, source))

    # ----------------------------------------------------------------------------------------- queries
    def robots(self) -> list[str | None]:
        return sorted({key_robot(k) for k in self.poses}, key=lambda r: (r is not None, r or ""))

    def keys(self) -> list[int]:
        return sorted(self.poses)

    def odometry(self) -> list[Edge]:
        return [e for e in self.edges if e.kind == ODOMETRY]

    def loops(self) -> list[Edge]:
        return [e for e in self.edges if e.kind == LOOP]

    def components(self) -> list[list[int]]:
        """Connected components (each a sorted key list), ordered by their smallest key."""
        parent = {k: k for k in self.poses}

        def find(k):
            while parent[k] != k:
                parent[k] = parent[parent[k]]
                k = parent[k]
            return k

        for e in self.edges:
            a, b = find(e.key_i), find(e.key_j)
            if a != b:
                parent[max(a, b)] = min(a, b)
        groups: dict[int, list[int]] = {}
        for k in sorted(self.poses):
            groups.setdefault(find(k), []).append(k)
        return sorted(groups.values(), key=lambda g: g[0])

    def anchors(self) -> list[int]:
        """One key per connected component to hold fixed: its smallest key (the lowest robot's first keyframe),
        so robots not yet connected to the others keep their own frame."""
        return [c[0] for c in self.components()]

    def merged(self, other: "PoseGraph") -> "PoseGraph":
        """Union of two graphs (e.g. two robots' files). Poses present in both keep this graph's value; an edge
        present in both (same keys, as DGS writes inter-robot edges into both robots' files) is kept once;
        pending edges whose two poses now exist become edges."""
        out = PoseGraph(dict(self.poses), [], self.is_2d and other.is_2d)
        for k, T in other.poses.items():
            out.poses.setdefault(k, T)
        seen = set()
        for e in self.edges + other.edges + self.pending + other.pending:
            if (e.key_i, e.key_j) in seen or (e.key_j, e.key_i) in seen:
                continue
            if e.key_i in out.poses and e.key_j in out.poses:
                out.edges.append(e)
                seen.add((e.key_i, e.key_j))
            else:
                out.pending.append(e)
        return out

    def with_poses(self, poses: dict[int, np.ndarray]) -> "PoseGraph":
        """Same edges, poses replaced (e.g. by an optimised estimate)."""
        return PoseGraph({k: np.asarray(poses[k], float) for k in self.poses}, list(self.edges), self.is_2d,
                         list(self.pending))


def is_odometry_pair(key_i: int, key_j: int) -> bool:
    """Consecutive keyframes of the same robot (the convention Kimera-RPGO and g2o files use)."""
    return key_robot(key_i) == key_robot(key_j) and abs(key_index(key_j) - key_index(key_i)) == 1


def check_information(info: np.ndarray, where: str) -> None:
    """InputError unless `info` is a finite, symmetric, positive-definite 6x6 matrix."""
    info = np.asarray(info)
    if info.shape != (6, 6):
        raise InputError(f"{where}: information matrix must be 6x6, got {list(info.shape)}")
    if not np.all(np.isfinite(info)):
        raise InputError(f"{where}: information matrix contains NaN or Inf")
    if not np.allclose(info, info.T, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(info).max()))):
        raise InputError(f"{where}: information matrix is not symmetric")
    try:
        np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        raise InputError(f"{where}: information matrix is not positive definite "
                         f"(eigenvalues {np.round(np.linalg.eigvalsh(info), 6).tolist()})") from None
