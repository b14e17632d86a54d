"""Sensor noise: a structured-light-like depth model and Gaussian colour noise, seeded per frame.

Depth, in order: axial Gaussian noise sigma(z) = a + b (z - c)^2 (Nguyen, Izadi, Lovell 2012, Kinect); disparity
quantisation (disparity = fb / z rounded to `disparity_step` pixels, so the depth step grows as z^2 / fb);
holes where the range is outside [min_m, max_m], where the surface is seen at a grazing angle, randomly on
depth discontinuities, and in a few clustered blobs. Each frame draws from its own generator seeded with
(seed, agent, frame), so output is identical whatever order frames are made in.
"""

from __future__ import annotations

import cv2
import numpy as np

from .config import ColorNoiseConfig, DepthNoiseConfig


def frame_rng(seed: int, agent: int, frame: int) -> np.random.Generator:
    return np.random.default_rng([seed, agent, frame, 11])


def depth_sigma(z: np.ndarray, cfg: DepthNoiseConfig) -> np.ndarray:
    """Axial noise standard deviation (metres) at range z (metres)."""
    a, b, c = cfg.sigma_m
    return a + b * (np.asarray(z) - c) ** 2


def noisy_depth(depth: np.ndarray, cos_incidence: np.ndarray, cfg: DepthNoiseConfig,
                rng: np.random.Generator) -> np.ndarray:
    """depth [H, W] float32 metres (0 = no hit), cos_incidence [H, W] -> noisy float32 depth, 0 = hole."""
    z = depth.astype(np.float32, copy=True)
    if not cfg.enabled:
        return z
    valid = (z >= cfg.min_m) & (z <= cfg.max_m) & (cos_incidence >= cfg.grazing_cos)
    z += rng.standard_normal(z.shape, dtype=np.float32) * depth_sigma(z, cfg).astype(np.float32)
    if cfg.disparity_step > 0:
        with np.errstate(divide="ignore", invalid="ignore"):
            disp = np.round(cfg.disparity_fb / z / cfg.disparity_step) * cfg.disparity_step
            z = np.where(disp > 0, cfg.disparity_fb / disp, 0.0).astype(np.float32)
    if cfg.edge_dropout > 0:
        valid &= ~(_discontinuities(depth) & (rng.random(z.shape, dtype=np.float32) < cfg.edge_dropout))
    if cfg.blob_holes > 0:
        valid &= ~_blobs(z.shape, cfg.blob_holes, rng)
    z[~valid] = 0.0
    return z


def _discontinuities(depth: np.ndarray, rel: float = 0.04) -> np.ndarray:
    """Pixels next to a jump in depth larger than `rel` of the range (either side of the edge)."""
    edge = np.zeros(depth.shape, dtype=bool)
    dx = np.abs(np.diff(depth, axis=1)) > rel * np.minimum(depth[:, 1:], depth[:, :-1])
    dy = np.abs(np.diff(depth, axis=0)) > rel * np.minimum(depth[1:], depth[:-1])
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    edge[1:] |= dy
    edge[:-1] |= dy
    return edge


def _blobs(shape: tuple[int, int], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """A mask covering about `fraction` of the image in smooth clustered blobs."""
    h, w = shape
    low = rng.standard_normal((max(h // 12, 2), max(w // 12, 2))).astype(np.float32)
    field = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    return field > np.quantile(low, 1.0 - fraction)


def noisy_color(color: np.ndarray, cfg: ColorNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """color [H, W, 3] float RGB in [0, 1] -> uint8 with additive Gaussian noise (sigma in 8-bit units)."""
    c = color * np.float32(255.0)
    if cfg.enabled and cfg.sigma > 0:
        c += rng.standard_normal(c.shape, dtype=np.float32) * np.float32(cfg.sigma)
    return np.clip(np.rint(c), 0, 255).astype(np.uint8)


def depth_to_uint16(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> uint16 PNG values (value = round(metres * depth_scale)); out-of-range becomes 0 (a hole)."""
    v = np.rint(depth.astype(np.float64) * depth_scale)
    v[(v < 0) | (v > 65535) | ~np.isfinite(v)] = 0
    return v.astype(np.uint16)
