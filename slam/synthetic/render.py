"""Colour and depth of the world from any camera pose, by ray casting (Open3D RaycastingScene, vectorised).

One ray per pixel through the pixel centre (u, v integer, as kernels.camera): its camera-frame direction is
K^-1 [u, v, 1], whose z component is 1, so the ray parameter at the hit *is* the depth (z in the camera frame).
Rays that hit nothing (impossible inside the closed world, possible from outside) give depth 0 and black.

With `supersample` s > 1, each pixel also casts s x s rays on a regular grid over its area (the rays of
camera.scaled(s W, s H)) and its colour is their mean: a sensor integrates the light over the pixel, and one ray
through the centre aliases every edge and fine texture (measured on the demo world at 320x240: the one-ray image
is only 28.6-31.3 dB from the 8 x 8 area mean, 2 x 2 rays 38.7-41.1 dB, 3 x 3 44.2-46.7 dB). Depth, incidence and
material stay the centre ray's: a structured-light sensor's depth is a per-pixel estimate, not an average.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from .config import MAX_SUPERSAMPLE
from .world import World


@dataclass
class Hits:
    """Noise-free render of a batch of frames."""

    depth: np.ndarray  # [N, H, W] float32 metres along the optical axis, 0 where nothing was hit
    color: np.ndarray  # [N, H, W, 3] float32 RGB in [0, 1]
    cos_incidence: np.ndarray  # [N, H, W] float32 |cos| of the angle between ray and surface normal
    material: np.ndarray  # [N, H, W] int64 material id, -1 where nothing was hit


@lru_cache(maxsize=8)
def _camera_rays(camera: PinholeCamera) -> np.ndarray:
    """[H*W, 3] float32 camera-frame ray directions with z = 1, row-major pixels."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    d = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
    return d.reshape(-1, 3).astype(np.float32)


@lru_cache(maxsize=8)
def _ray_lengths(camera: PinholeCamera) -> np.ndarray:
    """[H*W] float32 |K^-1 [u, v, 1]| per pixel."""
    return np.linalg.norm(_camera_rays(camera), axis=1).astype(np.float32)


def camera_for(width: int, height: int, hfov_deg: float) -> PinholeCamera:
    """A square-pixel pinhole camera with the principal point at the image centre."""
    fx = (width / 2.0) / np.tan(np.deg2rad(hfov_deg) / 2.0)
    return PinholeCamera(float(fx), float(fx), (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))


@dataclass
class Traced:
    """Raw ray-cast result of a batch of frames, before texturing (see `trace` and `shade`)."""

    rays: np.ndarray  # [N*H*W, 6] float32 world origin and direction (z = 1 in the camera)
    t_hit: np.ndarray  # [N*H*W] float32 depth, inf where nothing was hit
    prim: np.ndarray  # [N*H*W] triangle id
    shape: tuple[int, int, int]  # N, H, W


def trace(world: World, T_world_cam: np.ndarray, camera: PinholeCamera) -> Traced:
    """Ray-cast a batch of poses T_world_cam [N, 4, 4] (or [4, 4]) with Open3D (multi-threaded C++)."""
    import open3d as o3d

    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"T_world_cam must be finite [4, 4] or [N, 4, 4], got shape {list(T.shape)}")
    n, h, w = len(T), camera.height, camera.width
    # Open3D puts pixel centres at u + 0.5; shift the principal point so its rays pass through integer u, v.
    K = o3d.core.Tensor(camera.K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]))
    rays = np.empty((n, h * w, 6), dtype=np.float32)
    for k in range(n):  # C++ ray generation: directions R_world_cam K^-1 [u, v, 1], z = 1 in the camera
        r = o3d.t.geometry.RaycastingScene.create_rays_pinhole(K, o3d.core.Tensor(se3.inverse(T[k])), w, h)
        rays[k] = r.numpy().reshape(-1, 6)
    rays = rays.reshape(-1, 6)
    ans = world.scene.cast_rays(o3d.core.Tensor(rays))
    return Traced(rays, ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), (n, h, w))


def surface_coordinates(world: World, rays: np.ndarray, t: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s, t) [N] float32 texture coordinates of hits at ray parameter t of rays [N, 6] on triangles tri [N]: the two
    world axes in the face's plane, offset per face (texture.surface_offset)."""
    sa, ta = world.tri_surface_axes[tri, 0], world.tri_surface_axes[tri, 1]
    s = np.take_along_axis(rays, sa[:, None], 1)[:, 0] + np.take_along_axis(rays, sa[:, None] + 3, 1)[:, 0] * t
    s += world.tri_surface_offset[tri, 0]
    tt = np.take_along_axis(rays, ta[:, None], 1)[:, 0] + np.take_along_axis(rays, ta[:, None] + 3, 1)[:, 0] * t
    tt += world.tri_surface_offset[tri, 1]
    return s, tt


def shade_color(world: World, traced: Traced, camera: PinholeCamera) -> np.ndarray:
    """[N, H, W, 3] float32 colour of the hits of `trace` (black where a ray hit nothing): surface coordinates,
    pixel footprint and texture in one Warp CPU kernel (slam.synthetic.texture_kernel; safe to run in a worker
    thread, it releases the GIL). `shade_color_numpy` is its twin."""
    from .texture import COARSE_TEXEL_M, FINE_TEXEL_M
    from .texture_kernel import shade_rays_kernel

    n, h, w = traced.shape
    rgb = shade_rays_kernel(world, traced.rays, traced.t_hit, traced.prim, camera.fx, COARSE_TEXEL_M, FINE_TEXEL_M)
    return rgb.reshape(n, h, w, 3)


def shade_color_numpy(world: World, traced: Traced, camera: PinholeCamera) -> np.ndarray:
    """`shade_color` in NumPy (its twin, and the generator before the Warp texture kernel)."""
    n, h, w = traced.shape
    hit = np.isfinite(traced.t_hit) & (traced.t_hit > 0)
    idx = np.nonzero(hit)[0]
    t, tri, r = traced.t_hit[idx], traced.prim[idx].astype(np.int64), traced.rays[idx]
    s, tt = surface_coordinates(world, r, t, tri)
    footprint = t * (np.tile(_ray_lengths(camera), n)[idx] / np.float32(camera.fx))  # metres per pixel at the hit
    color = np.zeros((len(hit), 3), dtype=np.float32)
    color[idx] = world.texture.shade_numpy(s, tt, world.tri_material[tri], footprint, world.tri_light[tri])
    return color.reshape(n, h, w, 3)


def shade(world: World, traced: Traced, camera: PinholeCamera, *, texture: bool = True) -> Hits:
    """Depth, colour, incidence and material of the hits of `trace` (safe to run in a worker thread).
    texture=False leaves the colour black (depth, incidence and material only)."""
    rays, t_hit, prim = traced.rays, traced.t_hit, traced.prim
    n, h, w = traced.shape
    hit = np.isfinite(t_hit) & (t_hit > 0)
    all_hit = bool(hit.all())  # always, from inside the closed world: skip the gathers
    idx = slice(None) if all_hit else np.nonzero(hit)[0]
    t = t_hit[idx]
    tri = prim[idx].astype(np.int64)
    r = rays[idx]
    ray_len = np.tile(_ray_lengths(camera), n)[idx]
    mat_hit = world.tri_material[tri]
    color = (shade_color(world, traced, camera) if texture
             else np.zeros((n, h, w, 3), dtype=np.float32))
    # The faces are axis-aligned: |cos(incidence)| = |ray component along the normal's axis| / |ray|.
    cos_hit = np.abs(np.take_along_axis(r, world.tri_axis[tri][:, None] + 3, 1)[:, 0]) / ray_len
    if all_hit:
        depth, cos_inc, material = t_hit, cos_hit, mat_hit
    else:
        depth = np.where(hit, t_hit, 0.0).astype(np.float32)
        cos_inc = np.zeros(len(t_hit), dtype=np.float32)
        cos_inc[idx] = cos_hit
        material = np.full(len(t_hit), -1, dtype=np.int64)
        material[idx] = mat_hit
    return Hits(depth.reshape(n, h, w), color, cos_inc.reshape(n, h, w), material.reshape(n, h, w))


def check_supersample(supersample: int) -> int:
    ok = isinstance(supersample, (int, np.integer)) and not isinstance(supersample, bool)
    s = int(supersample) if ok else 0
    if not 1 <= s <= MAX_SUPERSAMPLE:  # the bound of GeneratorConfig.supersample
        raise InputError(f"supersample must be an integer from 1 to {MAX_SUPERSAMPLE} (rays per pixel side), "
                         f"got {supersample!r}")
    return s


def supersampled(camera: PinholeCamera, supersample: int) -> PinholeCamera:
    """The camera whose pixels are `supersample` x `supersample` sub-pixels of `camera`'s: its rays cover each
    pixel's area on a regular grid."""
    s = check_supersample(supersample)
    return camera if s == 1 else camera.scaled(camera.width * s, camera.height * s)


def combine(centre: Hits, fine_color: np.ndarray, supersample: int) -> Hits:
    """One pixel grid from `centre` (one ray per pixel centre, `shade(..., texture=False)` is enough) and
    `fine_color` [N, s H, s W, 3] (`shade_color` of the same poses through `supersampled(camera, s)`): colour is the
    mean of each pixel's s x s rays, depth, incidence and material are the centre ray's."""
    s = check_supersample(supersample)
    n, h, w = centre.depth.shape
    if fine_color.shape != (n, h * s, w * s, 3):
        raise InputError(f"combine: fine colour {list(fine_color.shape)} is not {s} x the centre's {[n, h, w, 3]}")
    color = fine_color.reshape(n, h, s, w, s, 3).mean(axis=(2, 4), dtype=np.float32)
    return Hits(centre.depth, color, centre.cos_incidence, centre.material)


def cast(world: World, T_world_cam: np.ndarray, camera: PinholeCamera, supersample: int = 1) -> Hits:
    """Ray-cast and texture a batch of poses: T_world_cam [N, 4, 4] (or [4, 4]) camera-to-world, with
    `supersample` x `supersample` rays per pixel (colour averaged; depth from the pixel-centre ray)."""
    s = check_supersample(supersample)
    if s == 1:
        return shade(world, trace(world, T_world_cam, camera), camera)
    fine = supersampled(camera, s)
    return combine(shade(world, trace(world, T_world_cam, camera), camera, texture=False),
                   shade_color(world, trace(world, T_world_cam, fine), fine), s)


def render(world: World, T_world_cam: np.ndarray, camera: PinholeCamera,
           supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free colour and depth of the world seen from one pose.

    T_world_cam: [4, 4] camera-to-world (OpenCV camera axes). Returns (color [H, W, 3] uint8 RGB,
    depth [H, W] float32 metres along the optical axis, 0 where no surface was hit). `supersample`: rays per
    pixel side, as `cast` (a dataset's frames use GeneratorConfig.supersample).
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"render: T_world_cam must be [4, 4], got {list(T.shape)}")
    hits = cast(world, T, camera, supersample)
    return to_uint8(hits.color[0]), hits.depth[0]


def to_uint8(color: np.ndarray) -> np.ndarray:
    """[..., 3] float RGB in [0, 1] -> uint8 (rounded)."""
    return np.clip(np.rint(color * 255.0), 0, 255).astype(np.uint8)
