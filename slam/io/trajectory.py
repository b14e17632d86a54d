"""Trajectory files: read and write TUM (`t x y z qx qy qz qw`, T_world_cam), as evo reads them.

Other formats (KITTI, EuRoC ground-truth CSV) are read here too; every reader reports file:line for a bad line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path, text_lines


def write_tum(path: str | Path, timestamps: np.ndarray, T_world_cam: np.ndarray) -> Path:
    """Write [N] timestamps and [N, 4, 4] poses as a TUM file, atomically. Refuses NaN poses."""
    timestamps = np.asarray(timestamps, dtype=np.float64)
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    if T_world_cam.ndim != 3 or T_world_cam.shape[1:] != (4, 4) or len(timestamps) != len(T_world_cam):
        raise InputError(f"write_tum({path}): expected [N] timestamps and [N, 4, 4] poses, got "
                         f"{list(timestamps.shape)} and {list(T_world_cam.shape)}")
    if not np.all(np.isfinite(T_world_cam)):
        bad = int(np.where(~np.isfinite(T_world_cam).reshape(len(T_world_cam), -1).all(1))[0][0])
        raise InputError(f"write_tum({path}): pose {bad} contains NaN or Inf")
    xyz, q = se3.to_tum(T_world_cam)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            f.write("# timestamp tx ty tz qx qy qz qw\n")
            for t, p, qq in zip(timestamps, xyz, q):
                f.write(f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {qq[0]:.9f} {qq[1]:.9f} {qq[2]:.9f} {qq[3]:.9f}\n")
    return Path(path)


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps [N], T_world_cam [N, 4, 4]). Comments (#) and blank lines skipped.

    Separators may be spaces, tabs or commas. A malformed line raises InputError naming file:line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    ts, rows = [], []
    for _, lineno, s in _open_lines(path):
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(f"{path}:{lineno}: expected 8 numbers 't x y z qx qy qz qw', got {len(parts)} fields")
        vals = _numbers(path, lineno, s)
        if np.linalg.norm(vals[4:8]) < 1e-9:
            raise InputError(f"{path}:{lineno}: quaternion has zero length")
        ts.append(vals[0])
        rows.append(vals[1:])
    if not rows:
        raise InputError(f"{path}: no poses found")
    a = np.asarray(rows)
    return np.asarray(ts), se3.from_tum(a[:, :3], a[:, 3:7])


# ---- other formats ------------------------------------------------------------------------------------------

TRAJECTORY_FORMATS = ("tum", "kitti", "euroc", "log")


@dataclass
class Trajectory:
    """Poses read from a file: T_world_cam [N, 4, 4] with timestamps [N] in seconds.

    `stamped` is False for formats without time (KITTI, Redwood .log): their timestamps are the frame
    indices 0, 1, 2, ... and such trajectories pair by index, not by time.
    """

    timestamps: np.ndarray  # [N] seconds (or frame indices when not stamped)
    T_world_cam: np.ndarray  # [N, 4, 4]
    stamped: bool
    path: Path
    fmt: str

    def __len__(self) -> int:
        return len(self.timestamps)


def _numbers(path: Path, lineno: int, s: str, sep: str | None = None) -> list[float]:
    parts = s.split(sep) if sep else s.replace(",", " ").split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{path}:{lineno}: not a number in {s!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise InputError(f"{path}:{lineno}: NaN or Inf in pose")
    return vals


def _check_rotation(path: Path, lineno: int, T: np.ndarray) -> None:
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-2 or np.linalg.det(R) <= 0:
        raise InputError(f"{path}:{lineno}: the 3x3 block is not a rotation matrix")


def _open_lines(path: str | Path):
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    for lineno, line in text_lines(path, "trajectory"):
        s = line.strip()
        if s and not s.startswith("#"):
            yield path, lineno, s


def read_kitti(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI pose file (12 numbers per line: the top 3x4 of T_world_cam, row-major) -> (indices [N], [N, 4, 4]).

    Lines of 16 numbers (full 4x4, as Replica's `traj.txt`) are accepted too. KITTI has no time: the returned
    timestamps are the frame indices.
    """
    poses = []
    for p, lineno, s in _open_lines(path):
        vals = _numbers(p, lineno, s)
        if len(vals) not in (12, 16):
            raise InputError(f"{p}:{lineno}: expected 12 numbers (3x4 pose, row-major), got {len(vals)} fields")
        T = np.eye(4)
        T[:3, :] = np.reshape(vals[:12], (3, 4))
        if len(vals) == 16 and not np.allclose(vals[12:], [0, 0, 0, 1], atol=1e-6):
            raise InputError(f"{p}:{lineno}: the last row of a 4x4 pose must be 0 0 0 1")
        _check_rotation(p, lineno, T)
        poses.append(T)
    if not poses:
        raise InputError(f"{path}: no poses found")
    return np.arange(len(poses), dtype=np.float64), np.stack(poses)


def read_euroc_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read EuRoC ground truth (`mav0/state_groundtruth_estimate0/data.csv`) -> (seconds [N], T_world_body [N, 4, 4]).

    Columns: timestamp [ns], p_RS_R x y z [m], q_RS w x y z, then velocities and biases (ignored). The pose is
    that of the body (IMU) frame; compose with the camera extrinsic T_body_cam for camera poses.
    """
    ts, rows = [], []
    for p, lineno, s in _open_lines(path):
        vals = _numbers(p, lineno, s, sep=",")
        if len(vals) < 8:
            raise InputError(f"{p}:{lineno}: expected at least 8 comma-separated numbers "
                             f"'t[ns], x, y, z, qw, qx, qy, qz', got {len(vals)}")
        if np.linalg.norm(vals[4:8]) < 1e-9:
            raise InputError(f"{p}:{lineno}: quaternion has zero length")
        ts.append(vals[0] * 1e-9)
        rows.append(vals[1:8])
    if not rows:
        raise InputError(f"{path}: no poses found")
    a = np.asarray(rows)
    return np.asarray(ts), se3.make(se3.quat_wxyz_to_matrix(a[:, 3:7]), a[:, :3])


def read_redwood_log(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a Redwood / ICL-NUIM `.log` trajectory -> (frame ids [N], T_world_cam [N, 4, 4]).

    Each entry is a header line `id id n` followed by the 4x4 camera-to-world matrix on 4 lines. The returned
    timestamps are the frame ids from the headers.
    """
    lines = list(_open_lines(path))
    if not lines:
        raise InputError(f"{path}: no poses found")
    if len(lines) % 5:
        p, lineno, _ = lines[-1]
        raise InputError(f"{p}:{lineno}: .log trajectory ends mid-entry (expected a header line and 4 matrix "
                         f"lines per pose, got {len(lines)} lines)")
    ids, poses = [], []
    for k in range(0, len(lines), 5):
        p, lineno, s = lines[k]
        head = _numbers(p, lineno, s)
        if len(head) != 3:
            raise InputError(f"{p}:{lineno}: expected a header 'id id n' (3 numbers), got {len(head)} fields")
        T = np.zeros((4, 4))
        for r in range(4):
            p, lineno, s = lines[k + 1 + r]
            row = _numbers(p, lineno, s)
            if len(row) != 4:
                raise InputError(f"{p}:{lineno}: expected 4 numbers (one matrix row), got {len(row)} fields")
            T[r] = row
        if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
            raise InputError(f"{p}:{lineno}: the last row of a 4x4 pose must be 0 0 0 1")
        _check_rotation(p, lines[k + 1][1], T)
        ids.append(head[0])
        poses.append(T)
    return np.asarray(ids, dtype=np.float64), np.stack(poses)


def detect_format(path: str | Path) -> str:
    """Guess a trajectory file's format from its suffix (.csv -> euroc, .log -> log) or its first pose line
    (8 numbers -> tum, 12 or 16 -> kitti)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return "euroc"
    if path.suffix.lower() == ".log":
        return "log"
    for p, lineno, s in _open_lines(path):
        n = len(s.replace(",", " ").split())
        if n == 8:
            return "tum"
        if n in (12, 16):
            return "kitti"
        raise InputError(f"{p}:{lineno}: cannot tell the trajectory format from a line of {n} fields "
                         f"(tum has 8, kitti 12); pass the format explicitly")
    raise InputError(f"{path}: no poses found")


def read_trajectory(path: str | Path, fmt: str = "auto") -> Trajectory:
    """Read a trajectory in any supported format: "tum", "kitti", "euroc" (ground-truth CSV), "log"
    (Redwood / ICL-NUIM), or "auto" (guessed by `detect_format`)."""
    fmt = (fmt or "auto").lower()
    if fmt not in TRAJECTORY_FORMATS + ("auto",):
        raise InputError(f"unknown trajectory format {fmt!r}; expected one of {', '.join(TRAJECTORY_FORMATS)} or auto")
    if fmt == "auto":
        fmt = detect_format(path)
    reader = {"tum": read_tum, "kitti": read_kitti, "euroc": read_euroc_csv, "log": read_redwood_log}[fmt]
    t, T = reader(path)
    return Trajectory(timestamps=t, T_world_cam=T, stamped=fmt in ("tum", "euroc"), path=Path(path), fmt=fmt)
