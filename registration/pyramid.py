"""One organised RGB-D frame's pyramid as projective ICP uses it, each level computed on first use and kept.

Frame-to-frame odometry registers frame n as the source of one pair and as the target of the next, and the
tracker's refinement takes the same frame's points again: with a `FramePyramid` per frame each level's vertex and
normal maps, valid points and smoothed intensity are computed once instead of once per use. The levels are exactly
what `registration.icp` computes without one (same operations on the same arrays), so results are unchanged.
"""

from __future__ import annotations

import numpy as np
import torch

from swarmsplat.kernels import icp as K
from swarmsplat.kernels.camera import PinholeCamera

from .pointcloud import gradient, intensity, level_camera, select_rows, smooth_and_stride


class FramePyramid:
    """Levels of one frame: `depth` [H, W] float32 metres (0 invalid), `color` [H, W, 3] uint8 or None, through
    `camera`, on torch device `device`. Levels are keyed by stride, depth cut-off (m, None for none) and the
    normals' depth-jump limit, so callers with different settings never share one."""

    def __init__(self, depth: np.ndarray, color: np.ndarray | None, camera: PinholeCamera, device="cpu"):
        self.depth = depth
        self.color = color
        self.camera = camera
        self.device = device
        self._cache: dict = {}

    def _memo(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def intensity(self) -> torch.Tensor:  # [H, W] float32 in [0, 1]
        return self._memo(("gray",), lambda: torch.from_numpy(intensity(self.color)).to(self.device))

    def depth_level(self, stride: int, depth_max: float | None) -> torch.Tensor:  # [h, w] metres, 0 beyond cut-off
        def make():
            d = torch.from_numpy(np.ascontiguousarray(self.depth[::stride, ::stride], dtype=np.float32))
            d = d.to(self.device)
            return d if depth_max is None else torch.where(d < depth_max, d, torch.zeros_like(d))

        return self._memo(("depth", stride, depth_max), make)

    def maps(self, stride: int, depth_max: float | None, jump: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(vertices [h, w, 3], normals [h, w, 3]) of the level (kernels.icp.vertices_normals_from_depth)."""
        return self._memo(("maps", stride, depth_max, jump), lambda: K.vertices_normals_from_depth(
            self.depth_level(stride, depth_max), level_camera(self.camera, stride), jump))

    def points(self, stride: int, depth_max: float | None, jump: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(points [N, 3], normals [N, 3], smoothed intensity [N] or None without colour) of the level's valid
        pixels, in row-major order."""
        def make():
            v, n = self.maps(stride, depth_max, jump)
            m = self.depth_level(stride, depth_max) > 0
            if self.color is None:
                return (*select_rows(m, v.reshape(-1, 3), n.reshape(-1, 3)), None)
            return tuple(select_rows(m, v.reshape(-1, 3), n.reshape(-1, 3), self.smoothed(stride).reshape(-1)))

        return self._memo(("points", stride, depth_max, jump), make)

    def smoothed(self, stride: int) -> torch.Tensor:  # [h, w] intensity box-filtered for the level
        return self._memo(("smoothed", stride), lambda: smooth_and_stride(self.intensity(), stride))

    def gradient(self, stride: int) -> torch.Tensor:  # [h, w, 2] of `smoothed`
        return self._memo(("gradient", stride), lambda: gradient(self.smoothed(stride)).contiguous())
