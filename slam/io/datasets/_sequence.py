"""`ImageSequence`: the one concrete `Sequence` every loader builds — lists of files, poses, a camera — loading
images lazily on indexing."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera

from ._images import check_size, read_color, read_depth
from .base import Frame


class FramesBase:
    """What every concrete `Sequence` shares: stamps `_t` [N], poses `_gt` / `_odom` [N, 4, 4] or None, iteration
    and the checked frame index."""

    name: str
    _t: np.ndarray
    _gt: np.ndarray | None
    _odom: np.ndarray | None

    def __len__(self) -> int:
        return len(self._t)

    def _checked_index(self, i) -> int:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {i} out of range for sequence '{self.name}' of {n} frames")
        return int(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def timestamps(self) -> np.ndarray:
        return self._t

    @property
    def gt_poses(self) -> np.ndarray | None:
        return self._gt

    @property
    def odometry(self) -> np.ndarray | None:
        return self._odom


class ImageSequence(FramesBase):
    """One agent's recording. Poses are T_world_cam [N, 4, 4]; a NaN row means "unknown for this frame"
    (e.g. EuRoC frames before motion capture starts)."""

    def __init__(
        self,
        *,
        name: str,
        root: Path,
        camera: PinholeCamera,
        timestamps: np.ndarray,  # [N] seconds
        color_paths: list[Path],
        depth_paths: list[Path] | None = None,
        depth_scale: float | None = None,
        gt_poses: np.ndarray | None = None,  # [N, 4, 4]
        odometry: np.ndarray | None = None,  # [N, 4, 4]
        color_transform: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        n = len(color_paths)
        assert len(timestamps) == n and (depth_paths is None or len(depth_paths) == n)
        assert gt_poses is None or gt_poses.shape == (n, 4, 4)
        assert odometry is None or odometry.shape == (n, 4, 4)
        self.name = name
        self.root = Path(root)
        self.camera = camera
        self._t = np.asarray(timestamps, dtype=np.float64)
        self.color_paths = list(color_paths)
        self.depth_paths = list(depth_paths) if depth_paths is not None else None
        self.depth_scale = depth_scale
        self._gt = gt_poses
        self._odom = odometry
        self._color_transform = color_transform

    @property
    def is_rgbd(self) -> bool:
        return self.depth_paths is not None

    def __getitem__(self, i: int) -> Frame:
        i = self._checked_index(i)
        cam = self.camera
        cp = self.color_paths[i]
        color = read_color(cp)
        if self._color_transform is not None:
            color = self._color_transform(color)
        check_size(cp, color, cam.width, cam.height)
        depth = None
        if self.depth_paths is not None:
            dp = self.depth_paths[i]
            depth = check_size(dp, read_depth(dp, self.depth_scale), cam.width, cam.height)
        return Frame(
            index=int(i),
            timestamp=float(self._t[i]),
            color=color,
            depth=depth,
            T_world_cam_gt=_row(self._gt, i),
            T_world_cam_odom=_row(self._odom, i),
        )

    def __repr__(self) -> str:
        kind = "rgbd" if self.is_rgbd else "mono"
        return f"ImageSequence({self.name!r}, {len(self)} {kind} frames, {self.camera.width}x{self.camera.height}, root={self.root})"


def _row(poses: np.ndarray | None, i: int) -> np.ndarray | None:
    if poses is None or not np.all(np.isfinite(poses[i])):
        return None
    return poses[i].copy()


def poses_at(stamps: np.ndarray, t_src: np.ndarray, T_src: np.ndarray, max_diff: float) -> np.ndarray:
    """Poses [N, 4, 4] at `stamps` [N] taken from the nearest source stamp within `max_diff` s; NaN where none."""
    from .associate import match_nearest

    out = np.full((len(stamps), 4, 4), np.nan)
    i, j = match_nearest(stamps, t_src, max_diff)
    out[i] = T_src[j]
    return out
