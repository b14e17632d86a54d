"""The procedural surface colour of slam.synthetic.texture as one Warp kernel (CPU), one thread per hit point.

`TextureField.shade_numpy` is its twin: the same formulas in NumPy, equal to 1e-4 at most and ~1e-5 on average
(float32 rounding of s / period, amplified by the stripe and plank profiles; tests/test_synthetic.py). The kernel
exists for speed: with several rays per pixel (GeneratorConfig.supersample) NumPy's temporaries made texturing
most of the generator's time. Warp's CPU backend runs a launch on the calling thread and releases the GIL, so the
generator's worker threads texture their batches in parallel.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
import warp as wp

from kernels._warp.arrays import to_warp
from kernels._warp.launch import run
from kernels.backend import _init_warp

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


@wp.kernel
def _shade(s_in: wp.array(dtype=float), t_in: wp.array(dtype=float), material: wp.array(dtype=wp.int32),
           footprint: wp.array(dtype=float), light: wp.array(dtype=float), coarse_img: wp.array2d(dtype=float),
           fine_img: wp.array2d(dtype=float), inv_coarse: float, inv_fine: float,
           color_a: wp.array2d(dtype=float), color_b: wp.array2d(dtype=float), color_c: wp.array2d(dtype=float),
           pattern: wp.array(dtype=wp.int32), period_of: wp.array(dtype=float), rgb: wp.array2d(dtype=float)):
    k = wp.tid()
    s = s_in[k]
    t = t_in[k]
    m = material[k]
    fp = footprint[k]
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
    gain = light[k] * (1.0 + 0.12 * fine)
    for ch in range(3):
        a = color_a[m, ch]
        c = a + mix * (color_b[m, ch] - a)
        c = c + accent * (color_c[m, ch] - c)
        rgb[k, ch] = wp.clamp(c * gain, 0.0, 1.0)


_FIRST = threading.Lock()  # the first launch compiles and loads the module: once, not from two worker threads
_loaded = False


def _t(a: np.ndarray, dtype) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype))


def shade_kernel(field, s: np.ndarray, t: np.ndarray, material: np.ndarray, footprint: np.ndarray,
                 light: np.ndarray, coarse_texel_m: float, fine_texel_m: float) -> np.ndarray:
    """[N, 3] float32 RGB of `field` (a texture.TextureField) at N surface points; see TextureField.shade."""
    n = len(s)
    out = np.empty((n, 3), dtype=np.float32)
    if n == 0:
        return out
    mt = field.materials
    keep = [_t(s, np.float32), _t(t, np.float32), _t(material, np.int32), _t(footprint, np.float32),
            _t(light, np.float32), _t(field.coarse, np.float32), _t(field.fine, np.float32)]
    tables = [_t(mt.color_a, np.float32), _t(mt.color_b, np.float32), _t(mt.color_c, np.float32),
              _t(mt.pattern, np.int32), _t(mt.period, np.float32)]
    rgb = torch.from_numpy(out)
    inputs = [to_warp(x) for x in keep] + [float(np.float32(1 / coarse_texel_m)), float(np.float32(1 / fine_texel_m))]
    inputs += [to_warp(x) for x in tables] + [to_warp(rgb)]
    global _loaded
    if not _loaded:
        with _FIRST:
            if not _loaded:
                _init_warp("cpu")  # quiet start-up, as the kernel backends
                run(_shade, n, inputs, "cpu")
                _loaded = True
                return out
    run(_shade, n, inputs, "cpu")
    return out
