"""Pinhole camera: intrinsics, projection, back-projection and resolution scaling.

Camera frame: x right, y down, z forward (OpenCV). Pixel centres sit at integer coordinates (u, v) with the
principal point (cx, cy) in the same convention, as in OpenCV, TUM and Open3D.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise InputError(f"camera field '{name}' is not finite: {v}")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"camera size must be positive, got {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """[3, 3] intrinsic matrix, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> "PinholeCamera":
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise InputError(f"intrinsic matrix K must be 3x3, got {list(K.shape)}")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same camera at another resolution (pixel-centre convention preserved)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, int(width), int(height)
        )

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[..., 3] camera-frame points -> (uv [..., 2] pixels, z [...] depth). Points with z <= 0 give NaN uv."""
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(z > 0, z, np.nan)
            u = self.fx * p[..., 0] / zs + self.cx
            v = self.fy * p[..., 1] / zs + self.cy
        return np.stack([u, v], axis=-1), z

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """[H, W] depth in metres -> [H, W, 3] camera-frame points (0 depth stays at the origin)."""
        depth = np.asarray(depth, dtype=np.float64)
        if depth.shape != (self.height, self.width):
            raise InputError(f"depth map has shape {list(depth.shape)}, camera expects [{self.height}, {self.width}]")
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        x = (u - self.cx) / self.fx * depth
        y = (v - self.cy) / self.fy * depth
        return np.stack([x, y, depth], axis=-1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5 + margin) & (u < self.width - 0.5 - margin) & (v >= -0.5 + margin) & (v < self.height - 0.5 - margin)

    def to_dict(self) -> dict:
        return dict(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, width=self.width, height=self.height)
