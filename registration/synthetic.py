"""A tiny analytic RGB-D renderer for tests and benchmarks: a textured box room with a few boxes inside.

Ray casting against axis-aligned boxes in NumPy (no Open3D, no files), so any resolution and pose can be made
on the fly. Colour is a smooth procedural texture of the world hit point, so two views of the same surface
agree (photometric consistency) and image gradients are well defined.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

ROOM = (np.array([-2.5, -1.5, -2.0]), np.array([2.5, 1.2, 3.5]))  # world frame, y down like the camera
BOXES = (
    (np.array([-1.2, 0.3, 1.5]), np.array([-0.4, 1.2, 2.3])),
    (np.array([0.6, -0.2, 2.0]), np.array([1.5, 1.2, 2.6])),
    (np.array([-0.3, 0.7, 0.8]), np.array([0.3, 1.2, 1.2])),
    (np.array([1.4, -1.5, -0.5]), np.array([2.5, -0.8, 0.5])),
)


def _slab(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
    return np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)


def texture(p: np.ndarray) -> np.ndarray:
    """[..., 3] world points -> [..., 3] RGB in [0, 1], smooth and non-periodic enough for alignment."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    r = 0.5 + 0.22 * np.sin(4.1 * x + 1.3 * z) + 0.18 * np.sin(6.3 * y - 2.9 * z + 0.5)
    g = 0.5 + 0.2 * np.sin(3.3 * z + 5.1 * y) * np.cos(2.2 * x) + 0.15 * np.sin(9.7 * x + 0.3)
    b = 0.5 + 0.25 * np.cos(5.3 * x - 3.7 * y + 2.1 * z)
    return np.clip(np.stack([r, g, b], -1), 0.0, 1.0)


def render(camera: PinholeCamera, T_world_cam: np.ndarray, *, room: bool = True,
           boxes=BOXES) -> tuple[np.ndarray, np.ndarray]:
    """-> (color uint8 [H, W, 3] RGB, depth float32 [H, W] metres along the optical axis, 0 = no hit)."""
    H, W = camera.height, camera.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = rays_cam @ R.T  # z-normalised in the camera, so the hit parameter is the depth
    o = np.broadcast_to(t, d.shape)
    best = np.full((H, W), np.inf)
    if room:
        _, t_exit = _slab(o, d, *ROOM)
        best = np.where(t_exit > 0, t_exit, best)
    for lo, hi in boxes:
        t_in, t_out = _slab(o, d, lo, hi)
        hit = (t_in <= t_out) & (t_in > 1e-6)
        best = np.where(hit & (t_in < best), t_in, best)
    ok = np.isfinite(best)
    depth = np.where(ok, best, 0.0)
    pts = o + d * depth[..., None]
    color = (texture(pts) * 255.0 + 0.5).astype(np.uint8)
    color[~ok] = 0
    return color, depth.astype(np.float32)


def default_camera(width: int = 640, height: int = 480) -> PinholeCamera:
    """A Kinect-like pinhole camera (fx = fy = 525 at 640x480) scaled to the given size."""
    return PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480).scaled(width, height)


def pose(xyz=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_world_cam from a position and small rotation angles (degrees) about the camera x, y, z axes."""
    return se3.make(se3.so3_exp(np.deg2rad(np.asarray(rpy_deg, np.float64))), np.asarray(xyz, np.float64))


def pair(width: int = 640, height: int = 480, dt=(0.04, -0.02, 0.03), drot_deg=(1.5, -2.0, 1.0)):
    """Two views of the room -> (camera, (color_s, depth_s), (color_t, depth_t), T_target_source true)."""
    cam = default_camera(width, height)
    T_w_t = pose((0.1, -0.1, -0.5), (-5.0, 8.0, 0.0))
    T_w_s = T_w_t @ pose(dt, drot_deg)
    cs, ds = render(cam, T_w_s)
    ct, dtg = render(cam, T_w_t)
    return cam, (cs, ds), (ct, dtg), se3.inverse(T_w_t) @ T_w_s
