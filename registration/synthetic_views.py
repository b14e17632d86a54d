"""Views of a textured room rendered by ray casting, with exact poses: the ground truth that tests and benchmarks
of place recognition and pair registration use when no recorded dataset is at hand.

The room is an axis-aligned box (walls, floor, ceiling) with a few axis-aligned blocks inside for parallax. Each
face carries its own procedural texture (random shapes, seeded), so places differ in appearance and corners are
plentiful for feature detectors. World axes follow the camera's OpenCV convention at identity: x right, y down,
z forward; poses are `T_world_cam`.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera


def _texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    import cv2

    img = np.full((size, size, 3), rng.integers(60, 200, 3), np.uint8)
    for _ in range(260):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        kind = rng.integers(3)
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(4, size // 10))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + r, y + int(rng.integers(4, size // 10))), colour, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), r // 2 + 2, colour, -1)
        else:
            cv2.line(img, (x, y), (x + int(rng.integers(-r, r)), y + int(rng.integers(-r, r))), colour, 3)
    return img


class TexturedRoom:
    """A box room [lo, hi] with `n_blocks` inner blocks; every face textured from `seed`."""

    def __init__(self, seed: int = 0, lo=(-4.0, -1.5, -4.0), hi=(4.0, 1.5, 4.0), n_blocks: int = 3):
        rng = np.random.default_rng(seed)
        self.boxes = [(np.asarray(lo, float), np.asarray(hi, float), True)]  # (lo, hi, seen from inside)
        for _ in range(n_blocks):
            c = rng.uniform([-2.5, 0.0, -2.5], [2.5, 1.0, 2.5])
            half = rng.uniform([0.3, 0.3, 0.3], [0.7, 1.2, 0.7])
            self.boxes.append((np.maximum(c - half, lo), np.minimum(c + half, hi), False))
        self.textures = [[_texture(rng) for _ in range(6)] for _ in self.boxes]

    def render(self, T_world_cam: np.ndarray, camera: PinholeCamera, supersample: int = 2):
        """-> (rgb uint8 [H, W, 3], depth float32 [H, W] metres along the optical axis)."""
        import cv2

        cam = camera.scaled(camera.width * supersample, camera.height * supersample)
        v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
        d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)  # z = 1 rays
        R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
        d = d_cam @ R.T  # [H, W, 3] world directions, length such that t = depth
        best_t = np.full(u.shape, np.inf)
        best_id = np.full(u.shape, -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            for b, (lo, hi, inside) in enumerate(self.boxes):
                t1, t2 = (lo - o) / d, (hi - o) / d
                tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
                if inside:  # leaving the room: nearest exit plane
                    t, axis = tmax.min(-1), tmax.argmin(-1)
                    sign = np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0
                    ok = np.isfinite(t) & (t > 0)
                else:  # entering a block: slab method
                    t, axis = tmin.max(-1), tmin.argmax(-1)
                    sign = np.take_along_axis(d, axis[..., None], -1)[..., 0] < 0
                    ok = (t > 1e-6) & (t <= tmax.min(-1))
                upd = ok & (t < best_t)
                best_t[upd] = t[upd]
                best_id[upd] = (b * 6 + axis * 2 + sign)[upd]
        out = np.zeros(u.shape + (3,), np.float32)
        p = o + d * np.where(np.isfinite(best_t), best_t, 0.0)[..., None]  # [H, W, 3] hit points
        for b, (lo, hi, _) in enumerate(self.boxes):
            for f in range(6):
                m = best_id == b * 6 + f
                if not m.any():
                    continue
                axis = f // 2
                a0, a1 = [a for a in range(3) if a != axis]
                tex = self.textures[b][f]
                s = tex.shape[0] - 1
                tu = (p[..., a0][m] - lo[a0]) / (hi[a0] - lo[a0]) * s
                tv = (p[..., a1][m] - lo[a1]) / (hi[a1] - lo[a1]) * s
                out[m] = _bilinear(tex, tu, tv)
        depth = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32)
        rgb = cv2.resize(out, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
        return np.clip(rgb + 0.5, 0, 255).astype(np.uint8), depth


def _bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample tex [S, S, 3] at float pixel coordinates x, y [M] -> [M, 3] float32."""
    s = tex.shape[0] - 1
    x, y = np.clip(x, 0, s), np.clip(y, 0, s)
    x0, y0 = np.minimum(x.astype(int), s - 1), np.minimum(y.astype(int), s - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    t = tex.astype(np.float32)
    top = t[y0, x0] * (1 - fx) + t[y0, x0 + 1] * fx
    bot = t[y0 + 1, x0] * (1 - fx) + t[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def look_pose(position, yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """T_world_cam at `position` turned by yaw (about world y, down), pitch (about x) and roll (about z)."""
    r = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    R = se3.so3_exp([0.0, r[0], 0.0]) @ se3.so3_exp([r[1], 0.0, 0.0]) @ se3.so3_exp([0.0, 0.0, r[2]])
    return se3.make(R, np.asarray(position, float))


def default_camera(width: int = 320, height: int = 240) -> PinholeCamera:
    """A ~70 degree horizontal field of view pinhole camera."""
    f = 0.7 * width
    return PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def relative_pose(T_world_query: np.ndarray, T_world_match: np.ndarray) -> np.ndarray:
    """T_query_match = T_world_query^-1 T_world_match: the match camera's pose in the query camera's frame."""
    return se3.inverse(T_world_query) @ T_world_match
