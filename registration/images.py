"""Checks and conversions for the images that enter place recognition and pair registration.

Every backend calls `as_rgb8` first, so a wrong array fails here with one clear `InputError` instead of deep
inside OpenCV or torch. Images are RGB uint8 [H, W, 3] (what `slam.io.datasets` returns); a single-channel uint8
[H, W] or [H, W, 1] image is accepted and replicated to three channels.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.errors import InputError

MIN_SIDE = 32  # below this no backend can find or describe structure reliably


def as_rgb8(image, name: str = "image", *, min_side: int = MIN_SIDE) -> np.ndarray:
    """Validate `image` and return it as a C-contiguous RGB uint8 [H, W, 3] array.

    Raises InputError naming `name` for: non-arrays, wrong rank or channel count, dtypes other than uint8
    (16-bit and float images must be converted by the caller, who knows their range), and images smaller than
    `min_side` pixels on a side.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected a numpy array [H, W, 3] uint8 RGB, got {type(image).__name__}")
    if image.dtype != np.uint8:
        hint = " (16-bit image: scale it to 8 bits first, e.g. (img >> 8).astype(np.uint8))" \
            if image.dtype == np.uint16 else ""
        raise InputError(f"{name}: expected dtype uint8, got {image.dtype}{hint}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise InputError(f"{name}: expected shape [H, W, 3] (RGB) or [H, W] (grey), got {list(image.shape)}")
    if image.shape[2] == 4:
        image = image[..., :3]
    h, w = image.shape[:2]
    if h < min_side or w < min_side:
        raise InputError(f"{name}: image of {w}x{h} pixels is too small; need at least {min_side}x{min_side}")
    return np.ascontiguousarray(image)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """RGB uint8 [H, W, 3] -> grey uint8 [H, W] (ITU-R 601 weights, as OpenCV)."""
    import cv2

    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def resize_max_side(rgb: np.ndarray, max_side: int | None) -> tuple[np.ndarray, tuple[float, float]]:
    """Downscale so the longer side is at most `max_side` (never upscale).

    Returns (image, (sx, sy)) with s = new size / old size per axis; a pixel maps back to the original image as
    x_old = (x_new + 0.5) / sx - 0.5 (pixel centres at integers, as `kernels.camera`).
    """
    import cv2

    h, w = rgb.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return rgb, (1.0, 1.0)
    s = max_side / max(h, w)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    out = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
    return out, (nw / w, nh / h)
