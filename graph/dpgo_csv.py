"""DPGO's multi-robot measurement files: a folder with one `robotN/measurements.csv` per robot.

Format (dpgo_ros' PGOLogger, as Kimera-Multi's teams record it), one header line then one row per measurement:

    robot_src,pose_src,robot_dst,pose_dst,qx,qy,qz,qw,tx,ty,tz,kappa,tau,is_known_inlier,weight

The row is the relative pose T_src^-1 T_dst (metres), weighted by SE-Sync's (kappa, tau): its information is
`graph.information.se_sync_information(kappa, tau)` = diag(2 kappa I, tau I). Robot N's keyframe i becomes the
GTSAM Symbol key (chr(ord('a') + N), i), as DGS writes its files. Same robot and pose_dst = pose_src + 1 is
odometry, every other row a loop closure. An inter-robot row appears in both robots' files; the copies must agree
(`weight`, the logged GNC weight of each robot, is not compared and not used). Initial poses are each robot's
odometry chained from the identity (the file has none).

Bad input raises InputError as one line naming file:line and the field: a missing column, a value that is not a
number, a non-unit quaternion, kappa or tau not positive, a row of robot N's file that does not involve robot N,
a loop to a robot that has no file, a pose id gap (a robot whose odometry does not reach every pose up to its
highest id), a pose of another robot beyond that robot's last pose, two copies of an inter-robot row that
disagree.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import text_lines

from .information import se_sync_information
from .pose_graph import LOOP, ODOMETRY, Edge, PoseGraph, robot_key

COLUMNS = ("robot_src", "pose_src", "robot_dst", "pose_dst", "qx", "qy", "qz", "qw", "tx", "ty", "tz", "kappa",
           "tau", "is_known_inlier", "weight")
_INTS = ("robot_src", "pose_src", "robot_dst", "pose_dst", "is_known_inlier")
_COMPARED = COLUMNS[4:14]  # what two copies of an inter-robot row must agree on
_QUAT_TOL = 1e-3  # |q| may differ from 1 by this (files print 6 significant digits)
MAX_ROBOTS = 150  # Symbol characters 'a' (97) .. 246; 0xFE is graph.formulations' scale character


def robot_char(n: int) -> str:
    """Symbol character of DPGO robot number n (0 -> 'a', as DGS's files)."""
    return chr(ord("a") + n)


def is_measurements_folder(path: str | Path) -> bool:
    p = Path(path)
    return p.is_dir() and any(p.glob("robot*/measurements.csv"))


def robot_files(folder: str | Path) -> dict[int, Path]:
    """Robot number -> its measurements.csv, from the folder's robotN/ subfolders."""
    out = {}
    for d in sorted(Path(folder).glob("robot*")):
        m = re.fullmatch(r"robot(\d+)", d.name)
        if m and (d / "measurements.csv").is_file():
            out[int(m.group(1))] = d / "measurements.csv"
    if not out:
        raise InputError(f"{folder}: no robotN/measurements.csv (DPGO's layout)")
    if max(out) >= MAX_ROBOTS:
        raise InputError(f"{out[max(out)]}: robot number {max(out)} too large (at most {MAX_ROBOTS - 1})")
    return out


def _read_rows(path: Path, robot: int, robots: set[int]) -> list[tuple[str, dict]]:
    """Rows of one file as (file:line, {column: value}) with every field checked."""
    lines = [line.rstrip("\r\n") for _, line in text_lines(path, "measurements.csv")]
    if not lines:
        raise InputError(f"{path}:1: empty file, expected the header {','.join(COLUMNS)}")
    header = [h.strip() for h in lines[0].split(",")]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise InputError(f"{path}:1: column {missing[0]!r} missing from the header (expected {','.join(COLUMNS)})")
    col = {c: header.index(c) for c in COLUMNS}
    rows = []
    for lineno, line in enumerate(lines[1:], 2):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        vals = line.split(",")
        if len(vals) != len(header):
            raise InputError(f"{where}: {len(vals)} fields, the header has {len(header)}")
        row = {}
        for c in COLUMNS:
            tok = vals[col[c]].strip()
            try:
                v = float(tok)
            except ValueError:
                raise InputError(f"{where}: field {c} is {tok!r}, not a number") from None
            if not np.isfinite(v):
                raise InputError(f"{where}: field {c} is {tok}, expected a finite number")
            if c in _INTS:
                if v != int(v) or v < 0:
                    raise InputError(f"{where}: field {c} is {tok}, expected a non-negative integer")
                v = int(v)
            row[c] = v
        if row["is_known_inlier"] not in (0, 1):
            raise InputError(f"{where}: field is_known_inlier is {row['is_known_inlier']}, expected 0 or 1")
        q = np.array([row["qx"], row["qy"], row["qz"], row["qw"]])
        if abs(np.linalg.norm(q) - 1.0) > _QUAT_TOL:
            raise InputError(f"{where}: fields qx,qy,qz,qw: quaternion has norm {np.linalg.norm(q):.6g}, expected 1")
        for c in ("kappa", "tau"):
            if not row[c] > 0:
                raise InputError(f"{where}: field {c} is {row[c]:g}, expected > 0")
        if robot not in (row["robot_src"], row["robot_dst"]):
            raise InputError(f"{where}: fields robot_src,robot_dst are {row['robot_src']},{row['robot_dst']}: a row "
                             f"of robot {robot}'s file must involve robot {robot}")
        for c in ("robot_src", "robot_dst"):
            if row[c] not in robots:
                raise InputError(f"{where}: field {c} is {row[c]}, a robot with no robot{row[c]}/measurements.csv")
        if (row["robot_src"], row["pose_src"]) == (row["robot_dst"], row["pose_dst"]):
            raise InputError(f"{where}: fields pose_src,pose_dst: a measurement from a pose to itself")
        rows.append((where, row))
    return rows


def _quat_xyzw_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def read_measurements(folder: str | Path) -> PoseGraph:
    """The team's pose graph from DPGO's `robotN/measurements.csv` files (module docstring)."""
    files = robot_files(folder)
    robots = set(files)
    per_robot = {r: _read_rows(p, r, robots) for r, p in files.items()}

    # each robot's own poses: 0..highest id, every step covered by an odometry row
    last: dict[int, int] = {}
    for r, rows in per_robot.items():
        odo = {row["pose_src"] for _, row in rows if row["robot_src"] == row["robot_dst"] == r
               and row["pose_dst"] == row["pose_src"] + 1}
        ids = sorted({row[p] for _, row in rows for rr, p in (("robot_src", "pose_src"), ("robot_dst", "pose_dst"))
                      if row[rr] == r} | {0})
        top = ids[-1]
        gap = next((i for i in range(top) if i not in odo), None)
        if gap is not None:
            where, field = _first_use(rows, r, gap + 1)
            raise InputError(f"{where}: field {field}: pose {gap + 1} of robot {r} has no odometry row from pose {gap} "
                             f"(pose id gap)")
        last[r] = top

    # merge: each row once, the copies of an inter-robot row compared
    seen: dict[tuple, tuple[str, dict]] = {}
    order: list[tuple] = []
    for r in sorted(per_robot):
        count: dict[tuple, int] = {}
        for where, row in per_robot[r]:
            for rr, p in (("robot_src", "pose_src"), ("robot_dst", "pose_dst")):
                if row[p] > last[row[rr]]:
                    raise InputError(f"{where}: field {p} is {row[p]}, but robot {row[rr]}'s poses end at "
                                     f"{last[row[rr]]}")
            ident = (row["robot_src"], row["pose_src"], row["robot_dst"], row["pose_dst"])
            count[ident] = count.get(ident, 0) + 1
            key = ident + (count[ident],)
            if key in seen:
                first_where, first = seen[key]
                if first_where.rsplit(":", 1)[0] != where.rsplit(":", 1)[0]:  # the other robot's copy
                    bad = [c for c in _COMPARED if not np.isclose(row[c], first[c], rtol=1e-6, atol=1e-9)]
                    if bad:
                        raise InputError(f"{where}: field {bad[0]} is {row[bad[0]]:g}, but the copy of this "
                                         f"inter-robot row at {first_where} has {first[bad[0]]:g}")
                    continue
            seen[key] = (where, row)
            order.append(key)

    graph = PoseGraph()
    for r in sorted(files):
        for i in range(last[r] + 1):
            graph.poses[robot_key(robot_char(r), i)] = np.eye(4)
    for key in order:
        where, row = seen[key]
        T = np.eye(4)
        T[:3, :3] = _quat_xyzw_matrix(np.array([row["qx"], row["qy"], row["qz"], row["qw"]]))
        T[:3, 3] = row["tx"], row["ty"], row["tz"]
        ki = robot_key(robot_char(row["robot_src"]), row["pose_src"])
        kj = robot_key(robot_char(row["robot_dst"]), row["pose_dst"])
        odometry = row["robot_src"] == row["robot_dst"] and row["pose_dst"] == row["pose_src"] + 1
        graph.edges.append(Edge(ki, kj, T, se_sync_information(row["kappa"], row["tau"]),
                                ODOMETRY if odometry else LOOP, source=where))
    _chain_odometry(graph)
    return graph


def _first_use(rows: list[tuple[str, dict]], robot: int, index: int) -> tuple[str, str]:
    """Where pose `index` of `robot` (or the first pose beyond it) first appears, and in which field."""
    best = None
    for where, row in rows:
        for rr, p in (("robot_src", "pose_src"), ("robot_dst", "pose_dst")):
            if row[rr] == robot and row[p] >= index and (best is None or row[p] < best[0]):
                best = (row[p], where, p)
    return best[1], best[2]


def _chain_odometry(graph: PoseGraph) -> None:
    """Each robot's poses as its odometry chained from the identity."""
    step = {e.key_i: e.T_ij for e in graph.edges if e.kind == ODOMETRY}
    for k in graph.keys():
        if k in step and k + 1 in graph.poses:
            graph.poses[k + 1] = graph.poses[k] @ step[k]
