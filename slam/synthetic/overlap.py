"""Ground-truth co-visibility between two views of a world: which surface one camera sees that another sees too.

Used by the tests of the trajectories (revisits, inter-agent and opposite-direction overlaps) and useful to
anyone who needs the true loop-closure pairs of a synthetic dataset.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

from .render import camera_for, cast
from .world import World


def covisibility(world: World, T_world_a: np.ndarray, T_world_b: np.ndarray, camera: PinholeCamera | None = None,
                 *, tolerance_m: float = 0.05) -> float:
    """Fraction of the surface points seen by camera a (one per pixel) that camera b sees as well, in [0, 1].

    A point counts when it projects inside b's image and b's own ray there stops within `tolerance_m` of it
    (so occluded points do not count). T_world_a, T_world_b: [4, 4] camera-to-world. A low-resolution camera
    (default 64x48) is plenty.
    """
    camera = camera or camera_for(64, 48, 62.8)
    hits = cast(world, np.stack([T_world_a, T_world_b]), camera)
    depth_a, depth_b = hits.depth[0], hits.depth[1]
    pts_a = camera.backproject(depth_a)[depth_a > 0]  # [P, 3] in camera a
    if len(pts_a) == 0:
        return 0.0
    T_b_a = se3.inverse(T_world_b) @ np.asarray(T_world_a)
    pts_b = pts_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    uv, z = camera.project(pts_b)
    ok = (z > 0) & camera.in_image(np.nan_to_num(uv, nan=-1e9))
    u = np.clip(np.rint(uv[ok, 0]).astype(int), 0, camera.width - 1)
    v = np.clip(np.rint(uv[ok, 1]).astype(int), 0, camera.height - 1)
    seen = np.abs(depth_b[v, u] - z[ok]) < tolerance_m + 0.01 * z[ok]
    return float(seen.sum() / len(pts_a))


def view_angle_deg(T_world_a: np.ndarray, T_world_b: np.ndarray) -> float:
    """Angle between the two optical axes, degrees (180 = looking in opposite directions)."""
    za, zb = np.asarray(T_world_a)[:3, 2], np.asarray(T_world_b)[:3, 2]
    return float(np.degrees(np.arccos(np.clip(za @ zb / (np.linalg.norm(za) * np.linalg.norm(zb)), -1, 1))))
