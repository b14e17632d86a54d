"""The procedural surface colour of slam.synthetic.texture as Warp CPU kernels, one thread per point.

`_shade` textures given surface points (TextureField.shade; `TextureField.shade_numpy` is its twin); `_shade_rays`
goes from ray-cast hits straight to colour: the hit's surface coordinates and pixel footprint (as
slam.synthetic.render computes them) and then the same texture function `_rgb` (render.shade_color;
render.shade_color_numpy is its twin). Both equal their twins to 1e-4 at most and ~1e-5 on average (float32
rounding of s / period, amplified by the stripe and plank profiles; tests/test_synthetic.py). The kernels exist
for speed: with several rays per pixel (GeneratorConfig.supersample) NumPy's temporaries made texturing most of
the generator's time (measured on 4 supersampled 320x240 frames: 127 ms per frame in NumPy, 30 ms in `_shade_rays`,
the other core busy). Warp's CPU backend runs a launch on the calling thread and releases the GIL, so the
generator's worker threads texture their batches in parallel.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
import warp as wp

from swarmsplat.kernels._warp.arrays import to_warp
from swarmsplat.kernels._warp.launch import run
from swarmsplat.kernels.backend import _init_warp

wp.set_module_options({"enable_backward": False})

# Pattern ids: the order of texture.PATTERNS ("noise", "stripes", "tiles", "planks", "blotches").
_NOISE, _STRIPES, _TILES, _PLANKS, _BLOTCHES = 0, 1, 2, 3, 4


@wp.func
def _bilinear(img: wp.array2d(dtype=float), s: float, t: float) -> float:
    h = img.shape[0] - 1
    w = img.shape[1] - 1
    i = int(s)
    j = int(t)
    fs = s - float(i)
    ft = t - float(j)
    r = i & (h - 1)
    c = j & (w - 1)
    p00 = img[r, c]
    p01 = img[r, c + 1]
    p10 = img[r + 1, c]
    p11 = img[r + 1, c + 1]
    top = p00 + ft * (p01 - p00)
    bot = p10 + ft * (p11 - p10)
    return top + fs * (bot - top)


@wp.func
def _soft_step(x: float, width: float) -> float:
    return wp.clamp(0.5 + x / width, 0.0, 1.0)


@wp.func
def _hash01(i: float, j: float, m: int) -> float:
    h = (wp.int64(i) * wp.int64(73856093)) ^ (wp.int64(j) * wp.int64(19349663)) ^ (wp.int64(m) * wp.int64(83492791))
    h = (h ^ (h >> wp.int64(13))) * wp.int64(1274126177)
    return float((h >> wp.int64(8)) & wp.int64(0xFFFF)) / 65535.0


@wp.func
def _rgb(s: float, t: float, m: int, fp: float, light: float, coarse_img: wp.array2d(dtype=float),
         fine_img: wp.array2d(dtype=float), inv_coarse: float, inv_fine: float, color_a: wp.array2d(dtype=float),
         color_b: wp.array2d(dtype=float), color_c: wp.array2d(dtype=float), pattern: wp.array(dtype=wp.int32),
         period_of: wp.array(dtype=float)) -> wp.vec3:
    coarse = _bilinear(coarse_img, s * inv_coarse, t * inv_coarse)
    fade = wp.clamp(2.0 - fp * inv_fine, 0.0, 1.0)
    fine = _bilinear(fine_img, s * inv_fine, t * inv_fine) * fade
    period = period_of[m]
    pat = pattern[m]
    mix = float(0.0)
    accent = float(0.0)
    if pat == _NOISE:
        mix = 0.5 + 0.35 * coarse + 0.25 * fine
        accent = _soft_step(coarse - 1.1, 0.15)
    elif pat == _STRIPES:
        phase = s / period + 0.08 * coarse
        dist = wp.abs(phase - wp.floor(phase) - 0.5) * period
        mix = 0.15 + 0.7 * _soft_step(dist - 0.25 * period, fp) + 0.1 * fine
        accent = _soft_step(coarse - 1.3, 0.2)
    elif pat == _TILES:
        i = wp.floor(s / period)
        j = wp.floor(t / period)
        tone = _hash01(i, j, m)
        du = wp.min(s / period - i, i + 1.0 - s / period) * period
        dv = wp.min(t / period - j, j + 1.0 - t / period) * period
        mix = 0.2 + 0.6 * tone + 0.15 * coarse + 0.1 * fine
        accent = _soft_step(0.006 - wp.min(du, dv), fp)
    elif pat == _PLANKS:
        j = wp.floor(t / period)
        shift = _hash01(j, j * 7.0 + 3.0, m) * 1.5
        i = wp.floor((s + shift) / 1.2)
        tone = _hash01(i, j, m)
        grain = 0.5 + 0.5 * wp.sin(2.0 * wp.pi * (t / (0.23 * period) + 1.5 * coarse + 0.4 * fine))
        dv = wp.min(t / period - j, j + 1.0 - t / period) * period
        du = wp.min((s + shift) / 1.2 - i, i + 1.0 - (s + shift) / 1.2) * 1.2
        fade_grain = wp.clamp(1.5 - fp / 0.01, 0.0, 1.0)
        mix = 0.275 + 0.5 * tone + 0.25 * (grain - 0.5) * fade_grain
        accent = _soft_step(0.004 - wp.min(du, dv), fp)
    else:  # blotches
        edge = 0.02 + fp
        second = wp.sin(3.0 * coarse + s * 1.3) * wp.cos(2.0 * coarse - t * 1.1)
        mix = _soft_step(coarse + 0.2 * fine, 8.0 * edge)
        accent = _soft_step(second - 0.55, 8.0 * edge)
    mix = wp.clamp(mix, 0.0, 1.0)
    accent = wp.clamp(accent, 0.0, 1.0)
    gain = light * (1.0 + 0.12 * fine)
    out = wp.vec3(0.0, 0.0, 0.0)
    for ch in range(3):
        a = color_a[m, ch]
        c = a + mix * (color_b[m, ch] - a)
        c = c + accent * (color_c[m, ch] - c)
        out[ch] = wp.clamp(c * gain, 0.0, 1.0)
    return out


@wp.kernel
def _shade(s_in: wp.array(dtype=float), t_in: wp.array(dtype=float), material: wp.array(dtype=wp.int32),
           footprint: wp.array(dtype=float), light: wp.array(dtype=float), coarse_img: wp.array2d(dtype=float),
           fine_img: wp.array2d(dtype=float), inv_coarse: float, inv_fine: float,
           color_a: wp.array2d(dtype=float), color_b: wp.array2d(dtype=float), color_c: wp.array2d(dtype=float),
           pattern: wp.array(dtype=wp.int32), period_of: wp.array(dtype=float), rgb: wp.array2d(dtype=float)):
    k = wp.tid()
    c = _rgb(s_in[k], t_in[k], material[k], footprint[k], light[k], coarse_img, fine_img, inv_coarse, inv_fine,
             color_a, color_b, color_c, pattern, period_of)
    for ch in range(3):
        rgb[k, ch] = c[ch]


@wp.kernel
def _shade_rays(rays: wp.array2d(dtype=float), t_hit: wp.array(dtype=float), prim: wp.array(dtype=wp.int32),
                axes: wp.array2d(dtype=wp.int32), offset: wp.array2d(dtype=float),
                tri_material: wp.array(dtype=wp.int32), tri_light: wp.array(dtype=float), inv_fx: float,
                coarse_img: wp.array2d(dtype=float), fine_img: wp.array2d(dtype=float), inv_coarse: float,
                inv_fine: float, color_a: wp.array2d(dtype=float), color_b: wp.array2d(dtype=float),
                color_c: wp.array2d(dtype=float), pattern: wp.array(dtype=wp.int32),
                period_of: wp.array(dtype=float), rgb: wp.array2d(dtype=float)):
    k = wp.tid()
    t = t_hit[k]
    if not (t > 0.0 and t < 1.0e30):  # a miss (inf) or a degenerate hit: black, as render.shade
        for ch in range(3):
            rgb[k, ch] = 0.0
        return
    tri = prim[k]
    sa = axes[tri, 0]
    ta = axes[tri, 1]
    s = rays[k, sa] + rays[k, sa + 3] * t + offset[tri, 0]
    tt = rays[k, ta] + rays[k, ta + 3] * t + offset[tri, 1]
    dx = rays[k, 3]
    dy = rays[k, 4]
    dz = rays[k, 5]
    fp = t * (wp.sqrt(dx * dx + dy * dy + dz * dz) * inv_fx)  # metres per pixel at the hit, along the ray
    c = _rgb(s, tt, tri_material[tri], fp, tri_light[tri], coarse_img, fine_img, inv_coarse, inv_fine, color_a,
             color_b, color_c, pattern, period_of)
    for ch in range(3):
        rgb[k, ch] = c[ch]


_FIRST = threading.Lock()  # the first launch compiles and loads the module: once, not from two worker threads
_loaded = False


def _t(a: np.ndarray, dtype) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype))


def _texture_inputs(field, coarse_texel_m: float, fine_texel_m: float) -> tuple[list, list]:
    """(kernel arguments of a texture.TextureField: its images, texel scales and material tables; the torch
    tensors they view, to keep alive until the launch returns)."""
    mt = field.materials
    images = [_t(field.coarse, np.float32), _t(field.fine, np.float32)]
    tables = [_t(mt.color_a, np.float32), _t(mt.color_b, np.float32), _t(mt.color_c, np.float32),
              _t(mt.pattern, np.int32), _t(mt.period, np.float32)]
    args = [to_warp(x) for x in images] + [float(np.float32(1 / coarse_texel_m)), float(np.float32(1 / fine_texel_m))]
    return args + [to_warp(x) for x in tables], images + tables


def _launch(kernel, n: int, inputs: list) -> None:
    global _loaded
    if not _loaded:
        with _FIRST:
            if not _loaded:
                _init_warp("cpu")  # quiet start-up, as the kernel backends
                run(kernel, n, inputs, "cpu")
                _loaded = True
                return
    run(kernel, n, inputs, "cpu")


def shade_kernel(field, s: np.ndarray, t: np.ndarray, material: np.ndarray, footprint: np.ndarray,
                 light: np.ndarray, coarse_texel_m: float, fine_texel_m: float) -> np.ndarray:
    """[N, 3] float32 RGB of `field` (a texture.TextureField) at N surface points; see TextureField.shade."""
    n = len(s)
    out = np.empty((n, 3), dtype=np.float32)
    if n == 0:
        return out
    points = [_t(s, np.float32), _t(t, np.float32), _t(material, np.int32), _t(footprint, np.float32),
              _t(light, np.float32)]
    tex, keep = _texture_inputs(field, coarse_texel_m, fine_texel_m)
    _launch(_shade, n, [to_warp(x) for x in points] + tex + [to_warp(torch.from_numpy(out))])
    del keep
    return out


def shade_rays_kernel(world, rays: np.ndarray, t_hit: np.ndarray, prim: np.ndarray, fx: float,
                      coarse_texel_m: float, fine_texel_m: float) -> np.ndarray:
    """[M, 3] float32 RGB of `world`'s surface where rays [M, 6] (world origin, direction with z = 1 in a camera
    of focal length fx) hit at ray parameter t_hit [M] on triangles prim [M]; black where t_hit is not a hit
    (inf or <= 0). The surface coordinates and pixel footprint of slam.synthetic.render, then the texture, in one
    pass (render.shade_color_numpy is its twin)."""
    m = len(t_hit)
    out = np.empty((m, 3), dtype=np.float32)
    if m == 0:
        return out
    # A miss carries Open3D's invalid id (uint32 max, -1 as int32); the kernel returns before reading it.
    per_ray = [_t(rays, np.float32), _t(t_hit, np.float32), _t(prim.astype(np.int32, copy=False), np.int32)]
    tables = [_t(world.tri_surface_axes, np.int32), _t(world.tri_surface_offset, np.float32),
              _t(world.tri_material, np.int32), _t(world.tri_light, np.float32)]
    tex, keep = _texture_inputs(world.texture, coarse_texel_m, fine_texel_m)
    _launch(_shade_rays, m, [to_warp(x) for x in per_ray + tables] + [float(np.float32(1 / fx))] + tex
            + [to_warp(torch.from_numpy(out))])
    del keep
    return out
