"""Trajectory files: read and write TUM (`t x y z qx qy qz qw`, T_world_cam), as evo reads them.

Other formats (KITTI, EuRoC ground-truth CSV) are read here too; every reader reports file:line for a bad line.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from kernels import se3
from kernels.errors import InputError
from kernels.fileio import atomic_path


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
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != 8:
                raise InputError(f"{path}:{lineno}: expected 8 numbers 't x y z qx qy qz qw', got {len(parts)} fields")
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                raise InputError(f"{path}:{lineno}: not a number in {s!r}") from None
            if not all(math.isfinite(v) for v in vals):
                raise InputError(f"{path}:{lineno}: NaN or Inf in pose")
            if np.linalg.norm(vals[4:8]) < 1e-9:
                raise InputError(f"{path}:{lineno}: quaternion has zero length")
            ts.append(vals[0])
            rows.append(vals[1:])
    if not rows:
        raise InputError(f"{path}: no poses found")
    a = np.asarray(rows)
    return np.asarray(ts), se3.from_tum(a[:, :3], a[:, 3:7])
