"""Loop-closure confidence from correspondence counts (FLOCC-SLAM §III-B, eqs. 1-2).

The front-end registers the loop pair (I_i^a, I_j^b) and also robot a's own odometry pair (I_{i-1}^a, I_i^a); the
ratio of their correspondence counts (eq. 1) is unitless. Below `r_thr` the registration is treated as failed;
above it, a logistic map (eq. 2) gives the probability p that multiplies the loop's information matrix.
"""

from __future__ import annotations

import math

import numpy as np

from swarmsplat.kernels.errors import InputError

R_THR_DEFAULT = 0.3  # the paper's correspondence-ratio threshold
K_DEFAULT = 5.0  # logistic steepness; the paper leaves k to tuning. p(r=1) = 0.5, p(r=0.3) = 0.03 with k = 5


def correspondence_ratio(n_pair: int, n_odom: int) -> float:
    """Eq. 1: r = |loop-pair correspondences| / |odometry-pair correspondences|.

    n_pair: correspondences between the two robots' keyframes; n_odom: between robot a's keyframe and its
    predecessor. Raises InputError for negative counts or n_odom == 0 (no reference to normalise by).
    """
    if n_pair < 0 or n_odom < 0:
        raise InputError(f"correspondence counts must be >= 0, got n_pair={n_pair}, n_odom={n_odom}")
    if n_odom == 0:
        raise InputError("correspondence_ratio: the odometry pair has 0 correspondences; cannot normalise")
    return float(n_pair) / float(n_odom)


def loop_confidence(ratio: float, k: float = K_DEFAULT, r_thr: float = R_THR_DEFAULT) -> float | None:
    """Eq. 2 behind the R_thr gate: None when `ratio < r_thr` (reject the loop), else
    p = 1 / (1 + exp(-k (ratio - 1))) in (0, 1)."""
    if not math.isfinite(ratio) or ratio < 0:
        raise InputError(f"loop_confidence: ratio must be a finite number >= 0, got {ratio}")
    if k <= 0:
        raise InputError(f"loop_confidence: k must be > 0, got {k}")
    if ratio < r_thr:
        return None
    return 1.0 / (1.0 + math.exp(-k * (ratio - 1.0)))


def scale_information(info: np.ndarray, p: float) -> np.ndarray:
    """Information matrix weighted by confidence p in (0, 1]: p * info (eq. 3's Omega(p))."""
    info = np.asarray(info, dtype=np.float64)
    if not (0.0 < p <= 1.0):
        raise InputError(f"scale_information: p must be in (0, 1], got {p}")
    return p * info
