"""Procedural surface colour: a deterministic field evaluated at ray hit points.

Every surface of the world is an axis-aligned box face, so a hit point has exact 2D surface coordinates (the
two world axes orthogonal to the face normal). Two tileable band-limited noise images (spectral synthesis,
generated once per world from its seed) are sampled there: a coarse one (features 0.12-1.5 m) that drives
colour variation and warps patterns, and a fine one (2.5-12 cm) that gives photometric trackers gradients at
every scale a 320x240 camera resolves. Each material adds a pattern (stripes, tiles, planks, blotches or plain
noise) with its own palette and period, so no two rooms look alike.

Anti-aliasing, cheaply: the fine layer fades towards its zero mean and pattern edges soften as the pixel
footprint (metres per pixel at the hit) grows, which is what a real pixel's integration does. Shading is
Lambertian under a fixed distant light, i.e. view-independent, so a surface has the same colour from every
viewpoint (the brightness-constancy that photometric SLAM assumes).
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

PATTERNS = ("noise", "stripes", "tiles", "planks", "blotches")
_LIGHT = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])

COARSE_TEXEL_M = 0.08  # 256 texels -> the coarse layer repeats every 20.5 m
FINE_TEXEL_M = 0.012  # 1024 texels -> the fine layer repeats every 12.3 m


@dataclass
class MaterialTable:
    """Per-material parameters, indexed by material id (arrays of length M)."""

    color_a: np.ndarray  # [M, 3] float32 RGB in [0, 1]
    color_b: np.ndarray  # [M, 3]
    color_c: np.ndarray  # [M, 3] accent (grout, spots, third camouflage colour)
    pattern: np.ndarray  # [M] int index into PATTERNS
    period: np.ndarray  # [M] float metres: stripe, tile or plank size
    offset: np.ndarray  # [M, 2] float metres added to surface coordinates, decorrelates materials

    def __len__(self) -> int:
        return len(self.pattern)


def _hsv(h: float, s: float, v: float) -> list[float]:
    return list(colorsys.hsv_to_rgb(h % 1.0, s, v))


def random_material(rng: np.random.Generator, pattern: str) -> dict:
    """One material's parameters: a palette with a strong light/dark contrast (trackers need gradients)."""
    hue = rng.random()
    sat = rng.uniform(0.2, 0.7)
    v_dark, v_light = rng.uniform(0.2, 0.4), rng.uniform(0.65, 0.95)
    a, b = _hsv(hue, sat, v_light), _hsv(hue + rng.uniform(-0.12, 0.12), sat * rng.uniform(0.6, 1.2), v_dark)
    c = _hsv(hue + rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.9), rng.uniform(0.15, 0.9))
    period = {"noise": 1.0, "stripes": rng.uniform(0.08, 0.3), "tiles": rng.uniform(0.2, 0.6),
              "planks": rng.uniform(0.1, 0.22), "blotches": 1.0}[pattern]
    return dict(color_a=a, color_b=b, color_c=c, pattern=PATTERNS.index(pattern), period=period,
                offset=rng.uniform(0.0, 50.0, size=2).tolist())


def material_table(materials: list[dict]) -> MaterialTable:
    f32 = lambda k: np.asarray([m[k] for m in materials], dtype=np.float32)  # noqa: E731
    return MaterialTable(f32("color_a"), f32("color_b"), f32("color_c"),
                         np.asarray([m["pattern"] for m in materials], dtype=np.int64), f32("period"), f32("offset"))


def _band_noise(rng: np.random.Generator, size: int, texel_m: float, lo_m: float, hi_m: float) -> np.ndarray:
    """Tileable noise [size, size] float32 with features between lo_m and hi_m, zero mean, unit std."""
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size, d=texel_m)[:, None]
    fx = np.fft.rfftfreq(size, d=texel_m)[None, :]
    f = np.sqrt(fx**2 + fy**2)  # cycles per metre
    band = (f >= 1.0 / hi_m) & (f <= 1.0 / lo_m)
    spectrum = np.fft.rfft2(white) * np.where(band, 1.0 / np.maximum(f, 1e-9), 0.0)  # pink within the band
    out = np.fft.irfft2(spectrum, s=(size, size))
    out = (out - out.mean()) / out.std()
    return out.astype(np.float32)


def _padded(img: np.ndarray) -> np.ndarray:
    """[H, W] tileable -> [H + 1, W + 1] with the first row and column repeated, so lookups never wrap."""
    return np.ascontiguousarray(np.pad(img, ((0, 1), (0, 1)), mode="wrap"))


def _bilinear(padded: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Sample a tileable image at non-negative texel coordinates s (rows), t (columns), wrapping.

    padded: the image from `_padded` (H, W powers of two). Coordinates must be >= 0 (truncation is floor).
    """
    h, w = padded.shape[0] - 1, padded.shape[1] - 1
    i, j = s.astype(np.int32), t.astype(np.int32)
    fs, ft = s - i, t - j
    idx = (i & (h - 1)) * (w + 1) + (j & (w - 1))
    flat = padded.ravel()
    p00, p01 = flat[idx], flat[idx + 1]
    idx += w + 1
    p10, p11 = flat[idx], flat[idx + 1]
    top = p00 + ft * (p01 - p00)
    bot = p10 + ft * (p11 - p10)
    return top + fs * (bot - top)


def _soft_step(x: np.ndarray, width: np.ndarray) -> np.ndarray:
    """0 for x << 0, 1 for x >> 0, linear across `width` (metres): an edge blurred to the pixel footprint."""
    return np.clip(0.5 + x / width, 0.0, 1.0)


def _hash01(i: np.ndarray, j: np.ndarray, m: np.ndarray) -> np.ndarray:
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (m.astype(np.int64) * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h >> 8) & 0xFFFF).astype(np.float32) / 65535.0


class TextureField:
    """The world's colour field: noise layers from the seed plus the material table."""

    def __init__(self, seed: int, materials: MaterialTable):
        rng = np.random.default_rng([seed, 7])
        self.coarse = _padded(_band_noise(rng, 256, COARSE_TEXEL_M, 0.12, 1.5))
        self.fine = _padded(_band_noise(rng, 1024, FINE_TEXEL_M, 0.025, 0.12))
        self.materials = materials
        self._b_minus_a = materials.color_b - materials.color_a

    def shade(self, s: np.ndarray, t: np.ndarray, material: np.ndarray, footprint: np.ndarray,
              light: np.ndarray) -> np.ndarray:
        """Colour of N surface points.

        s, t: [N] float32 surface coordinates in metres, >= 0 (the two world axes in the face's plane plus a
        per-material offset, see `surface_offset`); material: [N] int ids; footprint: [N] metres covered by
        one pixel at the hit; light: [N] Lambertian factor of the face (`lambert`). Returns [N, 3] float32 RGB
        in [0, 1]. Runs as a Warp kernel (slam.synthetic.texture_kernel); `shade_numpy` is its twin.
        """
        from .texture_kernel import shade_kernel

        return shade_kernel(self, s, t, material, footprint, light, COARSE_TEXEL_M, FINE_TEXEL_M)

    def shade_numpy(self, s: np.ndarray, t: np.ndarray, material: np.ndarray, footprint: np.ndarray,
                    light: np.ndarray) -> np.ndarray:
        """`shade` in NumPy (the kernel's twin; equal to 1e-4 at most, ~1e-5 on average)."""
        mt = self.materials
        fp = footprint
        coarse = _bilinear(self.coarse, s * np.float32(1 / COARSE_TEXEL_M), t * np.float32(1 / COARSE_TEXEL_M))
        fade = np.clip(np.float32(2.0) - fp * np.float32(1 / FINE_TEXEL_M), 0.0, 1.0)
        fine = _bilinear(self.fine, s * np.float32(1 / FINE_TEXEL_M), t * np.float32(1 / FINE_TEXEL_M))
        fine *= fade

        period = mt.period[material]
        mix = np.empty_like(s)  # weight of colour b
        accent = np.empty_like(s)  # weight of colour c
        pat = mt.pattern[material]
        kinds = np.bincount(pat, minlength=len(PATTERNS))
        for k, name in enumerate(PATTERNS):
            if kinds[k] == len(pat):  # one pattern in view: no gathers
                mix[:], accent[:] = _PATTERN_FNS[name](s, t, coarse, fine, period, fp, material)
            elif kinds[k]:
                sel = np.nonzero(pat == k)[0]
                mix[sel], accent[sel] = _PATTERN_FNS[name](s[sel], t[sel], coarse[sel], fine[sel], period[sel],
                                                          fp[sel], material[sel])
        np.clip(mix, 0.0, 1.0, out=mix)
        np.clip(accent, 0.0, 1.0, out=accent)
        rgb = mt.color_a[material]
        rgb += mix[:, None] * self._b_minus_a[material]
        rgb += accent[:, None] * (mt.color_c[material] - rgb)
        rgb *= (light * (np.float32(1.0) + np.float32(0.12) * fine))[:, None]
        return np.clip(rgb, 0.0, 1.0, out=rgb)


def lambert(normals: np.ndarray) -> np.ndarray:
    """[N, 3] unit normals -> [N] float32 brightness under the fixed distant light (view-independent)."""
    return (0.6 + 0.4 * np.abs(np.asarray(normals, dtype=np.float64) @ _LIGHT)).astype(np.float32)


def surface_offset(materials: MaterialTable, material: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """[N, 2] float32 offsets added to a face's surface coordinates: per material (so materials do not share
    a pattern phase) and per face orientation, plus 100 m so that coordinates are positive."""
    shift = np.asarray(axis, dtype=np.float32)[:, None] * np.array([3.1, 1.7], dtype=np.float32)
    return materials.offset[material] + shift + np.float32(100.0)


# Each pattern maps surface coordinates to (weight of colour b, weight of accent colour c), both [n] in [0, 1].

def _noise(s, t, coarse, fine, period, fp, m):
    return 0.5 + 0.35 * coarse + 0.25 * fine, _soft_step(coarse - 1.1, 0.15)


def _stripes(s, t, coarse, fine, period, fp, m):
    phase = s / period + 0.08 * coarse
    dist = np.abs(phase - np.floor(phase) - 0.5) * period  # metres from the stripe's centre line
    stripe = _soft_step(dist - 0.25 * period, fp)
    return 0.15 + 0.7 * stripe + 0.1 * fine, _soft_step(coarse - 1.3, 0.2)


def _tiles(s, t, coarse, fine, period, fp, m):
    i, j = np.floor(s / period), np.floor(t / period)
    tone = _hash01(i, j, m)
    du = np.minimum(s / period - i, i + 1 - s / period) * period
    dv = np.minimum(t / period - j, j + 1 - t / period) * period
    grout = _soft_step(0.006 - np.minimum(du, dv), fp)
    return 0.2 + 0.6 * tone + 0.15 * coarse + 0.1 * fine, grout


def _planks(s, t, coarse, fine, period, fp, m):
    j = np.floor(t / period)
    shift = _hash01(j, j * 7 + 3, m) * 1.5
    i = np.floor((s + shift) / 1.2)  # butt joints every 1.2 m, staggered per row
    tone = _hash01(i, j, m)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (t / (0.23 * period) + 1.5 * coarse + 0.4 * fine))
    dv = np.minimum(t / period - j, j + 1 - t / period) * period
    du = np.minimum((s + shift) / 1.2 - i, i + 1 - (s + shift) / 1.2) * 1.2
    seam = _soft_step(0.004 - np.minimum(du, dv), fp)
    fade = np.clip(1.5 - fp / 0.01, 0, 1)  # the grain averages out (to its mean) once a pixel spans it
    return 0.275 + 0.5 * tone + 0.25 * (grain - 0.5) * fade, seam


def _blotches(s, t, coarse, fine, period, fp, m):
    edge = 0.02 + fp  # sharp-edged patches: strong gradients at every distance
    second = np.sin(3.0 * coarse + s * 1.3) * np.cos(2.0 * coarse - t * 1.1)
    # The coarse layer changes by roughly 8 units per metre, so `8 * edge` is an edge about `edge` metres wide.
    return _soft_step(coarse + 0.2 * fine, 8.0 * edge), _soft_step(second - 0.55, 8.0 * edge)


_PATTERN_FNS = {"noise": _noise, "stripes": _stripes, "tiles": _tiles, "planks": _planks, "blotches": _blotches}
