"""Metric odometry with realistic drift, for the monocular variant (what VIO or wheel odometry would give).

The odometry frame is the agent's first camera frame: `T_odom_cam[0] = I`, and the ground-truth alignment
is `T_world_odom = T_world_cam_gt[0]`. Each frame-to-frame motion of the ground truth is corrupted by
- a translation scale (`MonoConfig.scale`, 1 = metric) and Gaussian translation noise whose sigma is
  `trans_noise` times the distance moved;
- a random rotation whose sigma grows with the distance moved (`rot_noise_deg_per_m`), and a heading bias
  about the world's vertical axis (`yaw_bias_deg_per_m`, a gyro bias), which is what makes odometry drift.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3

from .config import MonoConfig


def drifting_odometry(T_world_cam_gt: np.ndarray, cfg: MonoConfig, rng: np.random.Generator) -> np.ndarray:
    """[N, 4, 4] ground truth -> [N, 4, 4] T_odom_cam, starting at the identity."""
    T = np.asarray(T_world_cam_gt, dtype=np.float64)
    out = np.empty_like(T)
    out[0] = np.eye(4)
    up_world = np.array([0.0, 0.0, 1.0])
    for k in range(1, len(T)):
        rel = se3.inverse(T[k - 1]) @ T[k]  # T_cam(k-1)_cam(k)
        dist = float(np.linalg.norm(rel[:3, 3]))
        t = cfg.scale * rel[:3, 3] + rng.standard_normal(3) * cfg.trans_noise * dist
        up_cam = T[k - 1, :3, :3].T @ up_world
        w = (np.deg2rad(cfg.yaw_bias_deg_per_m) * dist * up_cam
             + rng.standard_normal(3) * np.deg2rad(cfg.rot_noise_deg_per_m) * dist)
        noisy = se3.make(se3.so3_exp(w) @ rel[:3, :3], t)
        out[k] = out[k - 1] @ noisy
    return out
