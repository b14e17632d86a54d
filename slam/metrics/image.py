"""Rendering quality: PSNR, SSIM and depth L1, on NumPy arrays or torch tensors (any device).

Colour images are [H, W, C] (channels last, as dataset frames) or [C, H, W] (channels first, as renders), with
C in {1, 3}; uint8 images are scaled to [0, 1], float images are taken as [0, 1]. Depth maps are [H, W] metres
with 0 (or non-finite) marking invalid ground truth. An optional boolean mask [H, W] restricts every metric.
All arithmetic is float64; results are Python floats.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from swarmsplat.kernels.errors import InputError


def _as_chw(name: str, img) -> torch.Tensor:
    """-> float64 [C, H, W] in [0, 1]."""
    t = torch.as_tensor(img) if not isinstance(img, torch.Tensor) else img
    is_uint8 = t.dtype == torch.uint8
    t = t.detach().to(torch.float64)
    if is_uint8:
        t = t / 255.0
    if t.dim() == 2:
        t = t[None]
    elif t.dim() == 3 and t.shape[-1] in (1, 3) and t.shape[0] not in (1, 3):
        t = t.permute(2, 0, 1)
    elif t.dim() == 3 and t.shape[0] in (1, 3):
        pass
    elif t.dim() == 3 and t.shape[-1] in (1, 3):
        t = t.permute(2, 0, 1)
    else:
        raise InputError(f"{name}: expected an image [H, W], [H, W, C] or [C, H, W] with C in 1 or 3, got {list(t.shape)}")
    return t


def _pair(pred, target) -> tuple[torch.Tensor, torch.Tensor]:
    p, g = _as_chw("pred", pred), _as_chw("target", target)
    if p.shape != g.shape:
        raise InputError(f"pred and target images differ in shape: {list(p.shape)} vs {list(g.shape)} (as [C, H, W])")
    return p, g.to(p.device)


def _mask(mask, shape_hw, device) -> torch.Tensor | None:
    if mask is None:
        return None
    m = torch.as_tensor(mask) if not isinstance(mask, torch.Tensor) else mask
    m = m.to(device=device).bool()
    if tuple(m.shape) != tuple(shape_hw):
        raise InputError(f"mask has shape {list(m.shape)}, expected {list(shape_hw)}")
    if not bool(m.any()):
        raise InputError("mask selects no pixels")
    return m


def psnr(pred, target, mask=None) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]: -10 log10(MSE) over all channels of the masked
    pixels. Identical images give +inf."""
    p, g = _pair(pred, target)
    m = _mask(mask, p.shape[1:], p.device)
    d2 = (p - g) ** 2
    mse = d2[:, m].mean() if m is not None else d2.mean()
    mse = float(mse)
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def _gaussian_window(size: int, sigma: float, device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(pred, target, mask=None, *, window: int = 11, sigma: float = 1.5) -> float:
    """Structural similarity (Wang et al. 2004) for images in [0, 1]: Gaussian window 11 / sigma 1.5,
    K1 = 0.01, K2 = 0.03, 'valid' filtering (no padding), averaged over channels and window positions.

    With a mask, the SSIM map is averaged over the window centres that fall on masked pixels.
    """
    p, g = _pair(pred, target)
    C, H, W = p.shape
    if H < window or W < window:
        raise InputError(f"SSIM needs images of at least {window}x{window} pixels, got {H}x{W}")
    m = _mask(mask, (H, W), p.device)
    w = _gaussian_window(window, sigma, p.device)
    if p.device.type == "cpu":
        smap = _ssim_map_cpu(p, g, w)  # [H - w + 1, W - w + 1, C] NumPy
    else:
        smap = _ssim_map_torch(p, g, w).permute(1, 2, 0)
    if m is not None:
        r = window // 2
        mc = m[r : H - r, r : W - r] if window % 2 else m[r : H - r + 1, r : W - r + 1]
        if not bool(mc.any()):
            raise InputError("mask selects no pixels away from the image border")
        return float(smap[mc.cpu().numpy() if isinstance(smap, np.ndarray) else mc].mean())
    return float(smap.mean())


_C1, _C2 = 0.01**2, 0.03**2


def _ssim_map_torch(p: torch.Tensor, g: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The SSIM map [C, H', W'] by torch convolutions (GPU tensors; on the CPU float64 convolutions take a slow
    path: ~270 ms for a 640x480 image pair)."""
    C, window = p.shape[0], w.shape[0]
    kx = w.view(1, 1, 1, -1).expand(C, 1, 1, window)
    ky = w.view(1, 1, -1, 1).expand(C, 1, window, 1)

    def blur(x):  # separable Gaussian, valid region only; x [1, C, H, W]
        x = torch.nn.functional.conv2d(x, kx, groups=C)
        return torch.nn.functional.conv2d(x, ky, groups=C)

    x, y = p[None], g[None]
    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    return (((2 * mu_x * mu_y + _C1) * (2 * sxy + _C2)) / ((mu_x**2 + mu_y**2 + _C1) * (sxx + syy + _C2)))[0]


def _ssim_map_cpu(p: torch.Tensor, g: torch.Tensor, w: torch.Tensor) -> np.ndarray:
    """The SSIM map [H', W', C] with OpenCV's separable float64 filter (the same sums as the torch convolutions,
    in another order: equal to ~1e-14). The filter's output at the window's anchor
    (its centre, window // 2) only reads pixels inside the image, so the 'valid' region is a crop of it. 640x480:
    ~40 ms against ~270 ms for the float64 convolutions on one torch thread."""
    import cv2

    window = w.shape[0]
    k = w.cpu().numpy()
    x = np.ascontiguousarray(p.cpu().numpy().transpose(1, 2, 0))  # [H, W, C] float64
    y = np.ascontiguousarray(g.cpu().numpy().transpose(1, 2, 0))
    H, W = x.shape[:2]
    a = window // 2

    def blur(z):
        out = cv2.sepFilter2D(z, cv2.CV_64F, k, k, anchor=(a, a), borderType=cv2.BORDER_REPLICATE)
        out = out.reshape(H, W, -1)  # OpenCV returns [H, W] for one channel
        return out[a : a + H - window + 1, a : a + W - window + 1]

    mu_x, mu_y = blur(x), blur(y)
    bxx, byy, bxy = blur(x * x), blur(y * y), blur(x * y)
    # the torch formula, in place: (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_xx + s_yy + C2))
    mx2, my2, mxy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    bxy -= mxy  # s_xy
    bxy *= 2
    bxy += _C2
    mxy *= 2
    mxy += _C1
    mxy *= bxy  # numerator
    bxx -= mx2  # s_xx
    byy -= my2  # s_yy
    bxx += byy
    bxx += _C2
    mx2 += my2
    mx2 += _C1
    mx2 *= bxx  # denominator
    mxy /= mx2
    return mxy


def depth_l1(pred_depth, gt_depth, mask=None) -> float:
    """Mean absolute depth error in metres over pixels where the ground truth is valid (> 0 and finite).

    pred_depth, gt_depth: [H, W] metres (NumPy or torch). Raises InputError when no pixel is valid.
    """
    p = (pred_depth if isinstance(pred_depth, torch.Tensor) else torch.as_tensor(np.asarray(pred_depth))).detach()
    g = (gt_depth if isinstance(gt_depth, torch.Tensor) else torch.as_tensor(np.asarray(gt_depth))).detach()
    p, g = p.to(torch.float64), g.to(torch.float64).to(p.device)
    if p.dim() == 3 and p.shape[0] == 1:
        p = p[0]
    if g.dim() == 3 and g.shape[0] == 1:
        g = g[0]
    if p.shape != g.shape or p.dim() != 2:
        raise InputError(f"depth maps must both be [H, W] of one size, got {list(p.shape)} and {list(g.shape)}")
    valid = torch.isfinite(g) & (g > 0) & torch.isfinite(p)
    m = _mask(mask, g.shape, g.device) if mask is not None else None
    if m is not None:
        valid &= m
    if not bool(valid.any()):
        raise InputError("depth L1: no pixel has valid ground-truth depth")
    return float((p[valid] - g[valid]).abs().mean())
