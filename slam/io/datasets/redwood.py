"""Redwood / Augmented ICL-NUIM RGB-D sequences (Choi, Zhou, Koltun 2015), as Open3D ships them:

    color/00000.jpg ...    depth/00000.png ... (uint16 millimetres, 0 = invalid)
    trajectory.log         ground truth, Redwood .log format (T_world_cam per frame id)
    odometry.log           optional odometry in the same format
    rgbd.match             optional 'depth/xxx.png color/xxx.jpg' pairs
    camera_*.json          optional Open3D intrinsics (column-major 3x3); PrimeSense defaults otherwise

The Augmented ICL-NUIM download names differ (`livingroom1-color/`, `livingroom1-depth-clean/`,
`livingroom1-traj.txt`); those are found too. Timestamps are frame index / fps (the sensor ran at 30 Hz).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import is_file
from swarmsplat.slam.io.trajectory import read_redwood_log

from ._sequence import ImageSequence

PRIMESENSE = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
REDWOOD_DEPTH_SCALE = 1000.0
_IMAGE_EXT = (".jpg", ".jpeg", ".png")


def _find_dir(root: Path, names: tuple[str, ...], suffixes: tuple[str, ...]) -> Path | None:
    for n in names:
        if (root / n).is_dir():
            return root / n
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if d.name.endswith(suffixes):
            return d
    return None


def _color_dir(root: Path) -> Path | None:
    return _find_dir(root, ("color", "image", "rgb"), ("-color", "_color"))


def _depth_dir(root: Path) -> Path | None:
    return _find_dir(root, ("depth",), ("-depth-clean", "-depth", "_depth"))


def _trajectory_file(root: Path) -> Path | None:
    for pattern in ("trajectory.log", "*traj*.log", "*-traj.txt", "*traj*.txt"):
        hits = sorted(root.glob(pattern))
        if hits:
            return hits[0]
    return None


def is_redwood_sequence(path: Path) -> bool:
    if not path.is_dir() or _color_dir(path) is None or _depth_dir(path) is None:
        return False
    return _trajectory_file(path) is not None or (path / "rgbd.match").is_file() or any(path.glob("*.log"))


def read_open3d_intrinsics(path: Path) -> PinholeCamera:
    """Open3D's PinholeCameraIntrinsic JSON: width, height, intrinsic_matrix (3x3, column-major)."""
    try:
        data = json.loads(path.read_text())
        K = np.asarray(data["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T
        return PinholeCamera.from_K(K, int(data["width"]), int(data["height"]))
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: not an Open3D camera intrinsics file ({e})") from None


def _images(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.suffix.lower() in _IMAGE_EXT)


def load_redwood_sequence(path: str | Path, *, camera: PinholeCamera | None = None, name: str | None = None,
                          fps: float = 30.0) -> ImageSequence:
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    cdir, ddir = _color_dir(root), _depth_dir(root)
    if cdir is None or ddir is None:
        raise InputError(f"{root}: expected colour and depth folders (color/ and depth/)")
    if (root / "rgbd.match").is_file():
        color, depth = _read_match(root / "rgbd.match")
    else:
        color, depth = _images(cdir), _images(ddir)
        if len(color) != len(depth):
            raise InputError(f"{root}: {cdir.name}/ holds {len(color)} images but {ddir.name}/ holds {len(depth)}")
    if not color:
        raise InputError(f"{root}: no images in {cdir.name}/")
    if camera is None:
        cams = sorted(root.glob("camera*.json"))
        camera = read_open3d_intrinsics(cams[0]) if cams else PRIMESENSE
    n = len(color)
    gt = _log_poses(_trajectory_file(root), n)
    odom = _log_poses(root / "odometry.log", n)
    return ImageSequence(name=name or root.name, root=root, camera=camera, timestamps=np.arange(n) / fps,
                         color_paths=color, depth_paths=depth, depth_scale=REDWOOD_DEPTH_SCALE, gt_poses=gt,
                         odometry=odom)


def _read_match(path: Path) -> tuple[list[Path], list[Path]]:
    color, depth = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 2:
            raise InputError(f"{path}:{lineno}: expected 'depth/file color/file', got {len(parts)} fields")
        d, c = path.parent / parts[0], path.parent / parts[1]
        for f in (d, c):
            if not is_file(f, f"{path}:{lineno}"):
                raise InputError(f"{path}:{lineno}: listed image not found: {f}")
        depth.append(d)
        color.append(c)
    return color, depth


def _log_poses(path: Path | None, n: int) -> np.ndarray | None:
    """Poses per frame from a .log file: the header's frame id says which frame each matrix belongs to."""
    if path is None or not path.is_file():
        return None
    ids, T = read_redwood_log(path)
    out = np.full((n, 4, 4), np.nan)
    for k, fid in enumerate(ids.astype(int)):
        if 0 <= fid < n:
            out[fid] = T[k]
    return out
