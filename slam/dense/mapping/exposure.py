"""The photometric model of a real camera: one affine colour transform per keyframe (exposure and white balance).

Consumer RGB-D cameras adjust exposure and white balance as they move. The map holds one colour per Gaussian, so
without a model of the camera each keyframe pulls the colours of the surfaces it shares with others toward its
own exposure, and a merged map, seen from a keyframe, shows other keyframes' exposures. Measured on the shared
HoloLens 2 office sequence (depth points of two frames that agree in 3D, reference poses): the per-channel gain
between two views of one surface spans 0.53-1.61 (5th-95th percentile of 155 pairs); one gain per pair takes the
colour RMSE between them from 0.185 to 0.125.

A keyframe k observes the map's colour c (what the rasteriser composites, alpha its coverage) as

    c_k = exp(g_k) * c + b_k * alpha          g_k, b_k in R^3 (log gain and offset per channel)

so the exposure is six numbers per keyframe, `e = [g_r, g_g, g_b, b_r, b_g, b_b]` (identity: zeros). The bias is
scaled by alpha so an empty pixel stays black, as without the model.

- At a new keyframe the exposure is *fitted* (`fit`, closed form, robust) to the render of the map that is
  already there: the active submap, or for a submap's first keyframe the previous submap, so every submap's
  colours stay in the gauge of the agent's first keyframe, as odometry chains poses. New Gaussians are seeded with
  the image's colour brought into that gauge (`unapply`).
- Mapping and the final map refinement optimise each keyframe's exposure with the map (Adam on `e`), regularised
  toward its fitted value; a submap's first keyframe (in mapping) and the agent's first keyframe (in refinement)
  hold the gauge.
- A frame whose exposure cannot be right (a black frame, an auto-exposure reset: a gain outside
  [1 / max_gain, max_gain] of its predecessor's or no agreeing pixels at all) is an *outlier*: it keeps its
  predecessor's exposure, its colour takes no part in the loss (its depth does), and metrics.json counts it.

    from swarmsplat.slam.dense.mapping.exposure import apply, fit
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

N_PARAMS = 6


def identity() -> np.ndarray:
    """The exposure that changes nothing: [6] zeros."""
    return np.zeros(N_PARAMS)


def apply(color: torch.Tensor, alpha: torch.Tensor, e: torch.Tensor | np.ndarray | None) -> torch.Tensor:
    """color [H, W, 3] as a keyframe of exposure e [6] sees it (alpha [H, W] the render's coverage);
    differentiable in color, alpha and e. None: unchanged."""
    if e is None:
        return color
    e = torch.as_tensor(e, dtype=color.dtype)
    return color * torch.exp(e[:3]) + alpha.unsqueeze(-1) * e[3:]


def unapply(color: np.ndarray, e: np.ndarray | None) -> np.ndarray:
    """[..., 3] colours a keyframe of exposure e saw, brought into the map's gauge (the inverse of `apply` at
    alpha 1), clipped to [0, 1]."""
    if e is None:
        return color
    e = np.asarray(e, dtype=np.float64)
    return np.clip((color - e[3:]) * np.exp(-e[:3]), 0.0, 1.0).astype(color.dtype)


@dataclass
class Fit:
    exposure: np.ndarray  # [6]
    pixels: int  # pixels the fit used (after trimming)
    rmse_before: float  # colour RMSE between the render and the image on those pixels, identity exposure
    rmse_after: float  # ... with the fitted exposure


def fit(rendered: np.ndarray, alpha: np.ndarray, rendered_depth: np.ndarray, image: np.ndarray, depth: np.ndarray,
        *, min_pixels: int = 500, depth_tolerance: float = 0.03) -> Fit | None:
    """The exposure e with image ≈ apply(rendered, alpha, e) on the pixels where the render is a surface the
    image also measured: alpha > 0.95, valid depth agreeing with the rendered depth within depth_tolerance
    (metres) + 3 %, neither value under- or over-exposed. The gain per channel is the ratio of the channel's sums
    (offsets start at 0; mapping and refinement optimise them): a least-squares slope would be pulled toward 0
    by the render's own error (regression dilution; on the analytic scene it found a gain of 0.41 for 0.60). Twice:
    the second pass drops the pixels whose residual exceeds 2.5x the first pass's median (specular highlights,
    moving things, occlusion edges). The render is divided by its alpha first: a composite that leaves a few
    percent of transmittance is that much darker than its surface, and keyframe after keyframe that bias would
    compound (measured on the HoloLens office: gains drifting to 8x over 45 submaps). None when fewer than
    `min_pixels` pixels qualify.

    rendered, image: [H, W, 3] in [0, 1]; alpha, rendered_depth, depth: [H, W] (metres, 0 = invalid)."""
    alpha = np.asarray(alpha, dtype=np.float64)
    rendered = np.asarray(rendered, dtype=np.float64) / np.maximum(alpha, 1e-6)[..., None]
    image = np.asarray(image, dtype=np.float64)
    ok = (alpha > 0.95) & (depth > 0) & (rendered_depth > 0)
    ok &= np.abs(rendered_depth - depth) < depth_tolerance + 0.03 * depth
    ok &= (image > 0.02).all(-1) & (image < 0.98).all(-1) & (rendered > 0.02).all(-1) & (rendered < 0.98).all(-1)
    if int(ok.sum()) < min_pixels:
        return None
    x, y = rendered[ok], image[ok]  # [P, 3]
    b = np.zeros(3)
    keep = np.ones(len(x), dtype=bool)
    for _ in range(2):
        a = y[keep].sum(axis=0) / x[keep].sum(axis=0)
        r = np.abs(y - x * a).max(axis=1)
        keep = r <= 2.5 * max(float(np.median(r)), 1e-3)
        if int(keep.sum()) < min_pixels:
            return None
    a = y[keep].sum(axis=0) / x[keep].sum(axis=0)
    e = np.concatenate([np.log(a), b])
    xs, ys = x[keep], y[keep]
    before = float(np.sqrt(np.mean((ys - xs) ** 2)))
    after = float(np.sqrt(np.mean((ys - (xs * a + b)) ** 2)))
    return Fit(e, int(keep.sum()), before, after)


def combine(fits: list[Fit]) -> Fit | None:
    """One exposure from fits of the same image against several parts of the map: their pixel-weighted mean
    (log gains and offsets alike); None when there is none."""
    if not fits:
        return None
    w = np.array([f.pixels for f in fits], dtype=np.float64)
    e = (np.stack([f.exposure for f in fits]) * w[:, None]).sum(axis=0) / w.sum()
    return Fit(e, int(w.sum()), float(np.average([f.rmse_before for f in fits], weights=w)),
               float(np.average([f.rmse_after for f in fits], weights=w)))


def is_outlier(e: np.ndarray, previous: np.ndarray, max_gain: float) -> bool:
    """True when exposure e is further than a factor max_gain from `previous` in any channel's gain, or its
    offset moves by more than a third of the range: no camera's auto exposure makes that step between two
    keyframes, a broken or black frame does."""
    e, previous = np.asarray(e), np.asarray(previous)
    return bool((np.abs(e[:3] - previous[:3]) > np.log(max_gain)).any() or (np.abs(e[3:] - previous[3:]) > 0.33).any())


def display_gain(keyframes) -> np.ndarray | None:
    """[3] exp(m), m the per-channel median log gain of `keyframes` (objects with `exposure` and `exposure_outlier`;
    outliers and those without an exposure left out): the colour a typical keyframe saw, relative to the map's own
    gauge. None when no keyframe has an exposure (the model was off: the map's colours are the images')."""
    es = [k.exposure for k in keyframes if k.exposure is not None and not k.exposure_outlier]
    if not es:
        return None
    return np.exp(np.median(np.stack(es)[:, :3], axis=0))


def for_display(params, keyframes):
    """`params` (GaussianParams) with its colours as a typical keyframe saw them, for map.ply and the viewer:
    clamp(colour, 0, 1) x display_gain(keyframes) per channel. The map's own colours hold the first keyframe's
    gauge, which drifts over a long walk of a real camera (docs/decisions/0011); these do not. A colour may pass 1:
    a 3DGS viewer clamps the composited pixel, not each splat, so every render of the written map equals the map
    seen with the median exposure. `params` itself is not changed; without exposures (the model off) the colours
    are only clamped to [0, 1], as rendered."""
    gain = display_gain(keyframes)
    with torch.no_grad():
        colors = params.colors.detach().clamp(0.0, 1.0)
        if gain is not None:
            colors = colors * torch.as_tensor(gain, dtype=colors.dtype)
    return dataclasses.replace(params.detached(), colors=colors)


def median_gauge(colors: torch.Tensor, keyframes, clip_fraction: float = 1.0) -> np.ndarray | None:
    """Bring a map's colours to its keyframes' median exposure, in place: m [3] the per-channel median log gain of
    `keyframes` (objects with `exposure`, `exposure_prior`, `exposure_outlier`; outliers and those without an
    exposure left out of the median), colours [N, 3] times exp(m), and m taken off every keyframe's log gain and
    its anchor. exp(g - m) * exp(m) c = exp(g) c: every exposed render stays as it was, except where a colour then
    passes 1 (the rasteriser clamps each Gaussian's colour): with clip_fraction < 1, m is lowered per channel
    until at most that fraction of the colours passes 1. Returns m, or None when no keyframe has an exposure.

    The gauge of the first keyframe, which mapping keeps, drifts over a long walk (docs/decisions/0011): the map's
    own colours, what map.ply and the viewer show, then match no image. At the median they look as a typical
    keyframe saw the scene."""
    es = [k.exposure for k in keyframes if k.exposure is not None and not k.exposure_outlier]
    if not es:
        return None
    m = np.median(np.stack(es)[:, :3], axis=0)
    with torch.no_grad():  # clamped first, as the rasteriser clamps them: then a darker gauge changes no render
        colors.clamp_(0.0, 1.0)
        if len(colors) and clip_fraction < 1:  # brighter only as far as few colours pass 1 (they would clip)
            q = np.quantile(colors.numpy(), 1.0 - clip_fraction, axis=0)
            m = np.minimum(m, -np.log(np.maximum(q, 1e-6)))
        colors.mul_(torch.as_tensor(np.exp(m), dtype=colors.dtype))
    for k in keyframes:
        for name in ("exposure", "exposure_prior"):
            e = getattr(k, name)
            if e is not None:
                e = np.array(e, dtype=np.float64)
                e[:3] -= m
                setattr(k, name, e)
    return m


def summary(exposures: list[np.ndarray | None], outliers: int) -> dict:
    """metrics.json's `exposure` block: how much the keyframes' exposures vary, and how many were outliers."""
    es = np.array([e for e in exposures if e is not None])
    if len(es) == 0:
        return {"model": "none", "keyframes": 0, "outlier_keyframes": int(outliers)}
    gains = np.exp(es[:, :3])
    return {"model": "affine per keyframe (gain and offset per channel)", "keyframes": len(es),
            "gain_min": float(gains.min()), "gain_median": float(np.median(gains)), "gain_max": float(gains.max()),
            "offset_abs_max": float(np.abs(es[:, 3:]).max()), "outlier_keyframes": int(outliers)}


def interpolated(keyframes, frame_index: int) -> np.ndarray | None:
    """The exposure of a frame that is not a keyframe: interpolated linearly (by frame index) between the
    keyframes before and after it, the nearest one's beyond the ends (None when the keyframes have none)."""
    kfs = [k for k in keyframes if k.exposure is not None]
    if not kfs:
        return None
    idx = np.array([k.frame_index for k in kfs])
    order = np.argsort(idx)
    idx = idx[order]
    es = np.stack([kfs[i].exposure for i in order])
    return np.array([np.interp(frame_index, idx, es[:, c]) for c in range(es.shape[1])])
