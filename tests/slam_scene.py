"""A tiny analytic RGB-D world for the SLAM tests: a textured box room with a cube inside, ray-cast exactly.

Self-contained on purpose (no generator, no files): any pose renders in milliseconds at 64x48.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

ROOM_LO, ROOM_HI = np.array([-2.0, -1.5, -1.0]), np.array([2.0, 1.5, 4.0])
BOX_LO, BOX_HI = np.array([-0.4, 0.2, 1.6]), np.array([0.3, 1.5, 2.2])


def camera(width: int = 64, height: int = 48) -> PinholeCamera:
    f = 0.9 * width
    return PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def _texture(p: np.ndarray) -> np.ndarray:
    # Two octaves (periods of about 2 m and 0.4 m) so photometric tracking has gradients at 64x48.
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    r = 0.5 + 0.2 * np.sin(3.1 * x + 1.7 * y) * np.cos(2.3 * z) + 0.2 * np.sin(15.0 * x + 9.0 * z)
    g = 0.5 + 0.2 * np.sin(2.2 * y - 2.9 * z + 0.5) + 0.2 * np.cos(13.0 * y - 11.0 * x)
    b = 0.5 + 0.2 * np.cos(2.7 * x + 1.9 * z - 0.3 * y) + 0.2 * np.sin(12.0 * z + 14.0 * y + 1.0)
    return np.clip(np.stack([r, g, b], -1), 0, 1)


def render(T_world_cam: np.ndarray, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(color uint8 [H, W, 3], depth float32 [H, W] metres along the optical axis)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = d_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        # leaving the room: the nearest exit plane
        t_room = np.maximum((ROOM_LO - o) * inv, (ROOM_HI - o) * inv).min(-1)
        # entering the box (slab method)
        t0, t1 = (BOX_LO - o) * inv, (BOX_HI - o) * inv
        t_in, t_out = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    hit_box = (t_in <= t_out) & (t_in > 0)
    t = np.where(hit_box & (t_in < t_room), t_in, t_room)
    p = o + d * t[..., None]
    color = (_texture(p) * 255).round().astype(np.uint8)
    return color, t.astype(np.float32)  # d_cam has z = 1, so t is the z-depth


def trajectory(n: int, *, radius: float = 0.3, step_deg: float = 3.0) -> np.ndarray:
    """n camera poses T_world_cam moving on a small arc while looking into the room (+z)."""
    poses = []
    for i in range(n):
        a = np.radians(step_deg * i)
        t = np.array([radius * np.sin(a), -0.1 + 0.05 * np.sin(2 * a), radius * (1 - np.cos(a)) - 0.3])
        w = np.array([0.05 * np.sin(a), a * 0.6, 0.0])
        poses.append(se3.make(se3.so3_exp(w), t))
    return np.stack(poses)
