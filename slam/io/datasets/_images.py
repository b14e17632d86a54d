"""Reading frames from disk with the checks every loader needs: colour -> RGB uint8, depth -> float32 metres."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError


def _imread(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot decode image: {path}")
    return img


def read_color(path: str | Path) -> np.ndarray:
    """8-bit colour or greyscale image -> [H, W, 3] uint8 RGB (greyscale is replicated, alpha dropped)."""
    import cv2

    path = Path(path)
    img = _imread(path)
    if img.dtype != np.uint8:
        raise InputError(f"{path}: colour image must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise InputError(f"{path}: unsupported colour image layout {list(img.shape)}")


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Single-channel uint16 depth PNG -> [H, W] float32 metres (value / depth_scale), 0 = invalid.

    An 8-bit or multi-channel image is refused: it is almost always a colour image or a lossy export, and
    reading it as depth would silently give a wrong scene.
    """
    path = Path(path)
    img = _imread(path)
    if img.ndim != 2:
        raise InputError(f"{path}: depth image must have one channel, got {img.shape[2]} channels")
    if img.dtype != np.uint16:
        raise InputError(f"{path}: depth image must be 16-bit (uint16), got {img.dtype}")
    return (img.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


def check_size(path: Path, img: np.ndarray, width: int, height: int) -> np.ndarray:
    if img.shape[0] != height or img.shape[1] != width:
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, calibration says {width}x{height}")
    return img
