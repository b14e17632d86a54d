"""Two-stage tracking (GRAND-SLAM §III-C): coarse frame-to-frame hybrid RGB-D odometry (eq. 4), then
frame-to-model refinement by the rasterisation pose gradient (eq. 5) with the Gaussians frozen.

The refinement optimises a twist xi = [omega, v] applied on the left of the world(local)-to-camera matrix,
viewmat = exp(xi) @ viewmat0: rotation and translation are expressed in the frame centred at the current camera,
not about the submap origin (the paper's "local" optimisation), with separate step sizes for the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from kernels import se3

from .config import TrackingConfig
from .frames import RGBD
from .gaussian_map import GaussianParams
from .odometry_adapter import Registration, coarse_odometry
from .render import render, rgbd_loss


@dataclass
class TrackResult:
    T_local_cam: np.ndarray  # [4, 4] refined pose in the active submap's frame
    T_local_cam_coarse: np.ndarray  # [4, 4] after the coarse stage
    coarse_ok: bool
    iterations: int
    loss: float
    coarse: Registration | None = None  # the coarse stage's registration (its information feeds the pose graph)


def refine_pose(params: GaussianParams, frame: RGBD, T_local_cam: np.ndarray, cfg: TrackingConfig,
                *, reference: bool = False) -> tuple[np.ndarray, int, float]:
    """Frame-to-model refinement over a resolution pyramid (coarsest first). Returns (pose, iterations, loss)."""
    frozen = params.detached()
    T_start = T = np.asarray(T_local_cam, dtype=np.float64)
    total_it, loss = 0, float("nan")
    for level in reversed(range(cfg.pyramid_levels)):
        f = frame.resized(max(16, cfg.refine_max_width >> level))
        iters = cfg.iterations if level == 0 else max(1, cfg.iterations // 2)
        T, it, loss = _refine_level(frozen, f, T, cfg, iters, reference)
        total_it += it
    if cfg.min_relative_gain > 0 and np.isfinite(loss):
        loss0 = tracking_loss(frozen, frame.resized(cfg.refine_max_width), T_start, cfg, reference)
        if not loss < (1.0 - cfg.min_relative_gain) * loss0:
            return T_start, total_it, loss0
    return T, total_it, loss


def tracking_loss(params: GaussianParams, f: RGBD, T_local_cam: np.ndarray, cfg: TrackingConfig,
                  reference: bool = False) -> float:
    """The eq.-5 tracking loss of `f` rendered at T_local_cam (no gradient)."""
    with torch.no_grad():
        out = render(params, torch.as_tensor(se3.inverse(T_local_cam), dtype=torch.float32), f.camera,
                     reference=reference)
        if float(out.alpha.max()) < cfg.alpha_min:
            return float("inf")
        return float(rgbd_loss(out, f.color_tensor(), f.depth_tensor(), lambda_color=cfg.lambda_color,
                               alpha_power=cfg.alpha_power, alpha_min=cfg.alpha_min, inlier_k=cfg.inlier_k,
                               normalise=True))


def _refine_level(params: GaussianParams, f: RGBD, T0: np.ndarray, cfg: TrackingConfig, iters: int,
                  reference: bool) -> tuple[np.ndarray, int, float]:
    color, depth = f.color_tensor(), f.depth_tensor()
    viewmat0 = torch.as_tensor(se3.inverse(T0), dtype=torch.float64)
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([{"params": [w], "lr": cfg.lr_rotation}, {"params": [v], "lr": cfg.lr_translation}])
    best = (float("inf"), np.zeros(6))
    still, it = 0, 0
    for it in range(1, iters + 1):
        opt.zero_grad(set_to_none=True)
        viewmat = se3.exp_torch(torch.cat([w, v])) @ viewmat0
        out = render(params, viewmat.float(), f.camera, reference=reference)
        if float(out.alpha.detach().max()) < cfg.alpha_min:
            break  # nothing of the model is visible: keep the coarse pose
        loss = rgbd_loss(out, color, depth, lambda_color=cfg.lambda_color, alpha_power=cfg.alpha_power,
                         alpha_min=cfg.alpha_min, inlier_k=cfg.inlier_k, normalise=True)
        lv = float(loss.detach())
        xi_now = torch.cat([w, v]).detach().numpy().copy()
        if lv < best[0]:
            best = (lv, xi_now)
        loss.backward()
        opt.step()
        dw = float((w.detach() - torch.as_tensor(xi_now[:3])).norm())
        dv = float((v.detach() - torch.as_tensor(xi_now[3:])).norm())
        still = still + 1 if (dw < cfg.converge_rot and dv < cfg.converge_trans) else 0
        if still >= cfg.patience:
            break
    if not np.isfinite(best[0]):
        return T0, it, float("nan")
    # viewmat = exp(xi) @ inv(T0)  =>  T_local_cam = T0 @ exp(xi)^-1
    return T0 @ se3.inverse(se3.exp(best[1])), it, best[0]


class Tracker:
    """Keeps the previous frame for the coarse stage and a constant-velocity fallback."""

    def __init__(self, cfg: TrackingConfig, *, max_depth: float = 10.0, reference: bool = False):
        self.cfg = cfg
        self.max_depth = max_depth
        self.reference = reference
        self._prev: RGBD | None = None
        self._prev_pose: np.ndarray | None = None  # T_local_cam of the previous frame (active submap frame)
        self._velocity = np.eye(4)  # T_prev_cur of the last step

    def reset_frame(self, T_new_old: np.ndarray) -> None:
        """Re-express the stored previous pose after the active submap's frame changes (new submap)."""
        if self._prev_pose is not None:
            self._prev_pose = np.asarray(T_new_old) @ self._prev_pose

    def track(self, frame: RGBD, params: GaussianParams) -> TrackResult:
        """Pose of `frame` in the active submap's local frame."""
        if self._prev is None:
            T = np.eye(4)
            self._remember(frame, T)
            return TrackResult(T, T, True, 0, 0.0)
        coarse_ok, r = False, None
        T_prev_cur = self._velocity
        if self.cfg.coarse == "rgbd_odometry":
            src = frame.resized(self.cfg.coarse_max_width)
            tgt = self._prev.resized(self.cfg.coarse_max_width)
            r = coarse_odometry(src, tgt, self._velocity, max_depth=self.max_depth)
            coarse_ok = r.success and float(np.linalg.norm(r.T_target_source[:3, 3])) <= self.cfg.coarse_max_motion
            if coarse_ok:
                T_prev_cur = r.T_target_source
        T_coarse = self._prev_pose @ T_prev_cur
        T, it, loss = T_coarse, 0, float("nan")
        refine = self.cfg.refine or (self.cfg.refine_on_coarse_failure and not coarse_ok)
        if refine and self.cfg.iterations > 0 and len(params) > 0:
            T, it, loss = refine_pose(params, frame, T_coarse, self.cfg, reference=self.reference)
        self._velocity = se3.inverse(self._prev_pose) @ T
        self._remember(frame, T)
        return TrackResult(T, T_coarse, coarse_ok, it, loss, r)

    def _remember(self, frame: RGBD, T: np.ndarray) -> None:
        self._prev = frame.resized(self.cfg.coarse_max_width)
        self._prev_pose = T
