"""Replica as NICE-SLAM / Gaussian-SLAM lay it out, and Multiagent Replica as CP-SLAM (and MAGiC-SLAM) do.

One scene (Gaussian-SLAM):      <scene>/results/frame000000.jpg, depth000000.png (uint16, 6553.5 per metre)
                                <scene>/traj.txt  (one T_world_cam per line, 16 numbers row-major)
Multiagent Replica (CP-SLAM):   <scene>/<agent folder>/ each laid out as above, agents in sorted name order.

Intrinsics are Replica's 1200x680 render camera (fx = fy = 600, cx = 599.5, cy = 339.5) unless a NICE-SLAM
`cam_params.json` sits in the scene folder or one of its two parents. CP-SLAM's trajectories sometimes hold
more poses than frames; the extra poses are dropped (fewer poses than frames is an error). Timestamps are
frame index / fps.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import read_kitti

from ._sequence import ImageSequence
from .base import MultiAgentDataset

REPLICA_CAMERA = PinholeCamera(600.0, 600.0, 599.5, 339.5, 1200, 680)
REPLICA_DEPTH_SCALE = 6553.5


def is_replica_sequence(path: Path) -> bool:
    return (path / "traj.txt").is_file() and (path / "results").is_dir()


def _cam_params(root: Path) -> tuple[PinholeCamera, float] | None:
    for d in (root, root.parent, root.parent.parent):
        f = d / "cam_params.json"
        if f.is_file():
            try:
                c = json.loads(f.read_text())["camera"]
                cam = PinholeCamera(float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]), int(c["w"]), int(c["h"]))
                return cam, float(c.get("scale", REPLICA_DEPTH_SCALE))
            except (ValueError, KeyError, TypeError) as e:
                raise InputError(f"{f}: expected {{'camera': {{w, h, fx, fy, cx, cy, scale}}}} ({e})") from None
    return None


def load_replica_sequence(path: str | Path, *, camera: PinholeCamera | None = None,
                          depth_scale: float | None = None, name: str | None = None, fps: float = 30.0) -> ImageSequence:
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    res = root / "results"
    color = sorted(res.glob("frame*.jpg")) + sorted(res.glob("frame*.png"))
    depth = sorted(res.glob("depth*.png"))
    if not color:
        raise InputError(f"{res}: no frame*.jpg images")
    if len(color) != len(depth):
        raise InputError(f"{res}: {len(color)} colour frames but {len(depth)} depth frames")
    _, T = read_kitti(root / "traj.txt")
    if len(T) < len(color):
        raise InputError(f"{root / 'traj.txt'}: {len(T)} poses for {len(color)} frames")
    found = _cam_params(root)
    cam = camera or (found[0] if found else REPLICA_CAMERA)
    scale = depth_scale or (found[1] if found else REPLICA_DEPTH_SCALE)
    n = len(color)
    return ImageSequence(name=name or root.name, root=root, camera=cam, timestamps=np.arange(n) / fps,
                         color_paths=color, depth_paths=depth, depth_scale=scale, gt_poses=T[:n])


def is_replica_multiagent(path: Path) -> bool:
    return path.is_dir() and len(_agent_dirs(path)) >= 1 and not is_replica_sequence(path)


def _agent_dirs(path: Path) -> list[Path]:
    return [d for d in sorted(path.iterdir()) if d.is_dir() and is_replica_sequence(d)]


def load_replica_multiagent(path: str | Path, **kw) -> MultiAgentDataset:
    """A Multiagent Replica scene: every sub-folder laid out as a Replica sequence is one agent."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"dataset folder not found: {root}")
    dirs = _agent_dirs(root)
    if not dirs:
        raise InputError(f"{root}: no agent sub-folders with results/ and traj.txt")
    return MultiAgentDataset(root=root, agents=[load_replica_sequence(d, **kw) for d in dirs], name=root.name,
                             kind="rgbd", meta={"layout": "replica-multiagent"})
