"""Mapping (GRAND-SLAM §III-B): seed Gaussians where the active submap is sparse, then optimise every Gaussian of
the active submap over its keyframes with the eq.-3 loss, then prune.

Seeding: render the submap at the new keyframe; where rendered alpha < α_min, back-project pixels on a regular
grid (one per stride x stride block: uniform sampling of the sparse region) to new Gaussians whose radius matches
the pixel footprint at their depth. Large regions without valid depth get a fallback depth (`fallback_depth`,
`mapping.seed_without_depth`): with none, a window or the sky beyond the sensor's range stays empty and renders
black (on Redwood 211, 77-96 % of the squared colour error of the worst keyframes was on those pixels).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
import torch

from swarmsplat.kernels.errors import SanityError
from swarmsplat.slam.config import ExposureConfig, MappingConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianMap, GaussianParams, Submap
from swarmsplat.slam.dense.param_ops import Activated, activate, isotropic_penalty
from swarmsplat.slam.dense.render import render, rgbd_loss_fused, viewmat_from_pose
from .exposure import apply, unapply


@dataclass
class MapKeyframe:
    """What mapping needs of a keyframe: its pose in the submap frame and its images at mapping resolution."""

    T_local_cam: np.ndarray  # [4, 4]
    rgbd: RGBD
    # slam.dense.mapping.exposure: the keyframe's exposure [6] (optimised in place unless `exposure_fixed`; None:
    # no photometric model), its regulariser's anchor, and whether its colour is an outlier left out of the loss.
    exposure: np.ndarray | None = None
    exposure_prior: np.ndarray | None = None
    exposure_fixed: bool = False
    exposure_outlier: bool = False


@dataclass
class MappingStats:
    added: int
    pruned: int
    iterations: int
    loss_first: float
    loss_last: float


def mapping_loss(out, color: torch.Tensor, depth: torch.Tensor, params: GaussianParams, cfg: MappingConfig,
                 lambda_color: float, isotropic_regulariser: float, activated: Activated | None = None
                 ) -> torch.Tensor:
    """Eq. 3 (masked colour + depth loss with cfg's alpha and inlier masks) plus the isotropic-scale penalty on the
    rendered Gaussians `params` (taken from `activated`, their `slam.dense.param_ops.activate`, when given); shared by
    submap mapping and the server's global refinement. Eq. 3 runs as kernels (slam.dense.render.rgbd_loss_fused, equal
    to slam.dense.render.rgbd_loss)."""
    loss = rgbd_loss_fused(out, color, depth, lambda_color=lambda_color, alpha_power=cfg.alpha_power,
                           inlier_k=cfg.inlier_k)
    if isotropic_regulariser > 0:
        iso = activated.isotropic if activated is not None else isotropic_penalty(params.scales)
        loss = loss + isotropic_regulariser * iso
    return loss


def seed_gaussians(submap: Submap, kf: MapKeyframe, cfg: MappingConfig, *, generator: torch.Generator
                   ) -> GaussianParams:
    """New Gaussians (submap-local frame) for the parts of `kf` the submap does not cover yet."""
    f = kf.rgbd
    cam = f.camera
    depth = f.depth
    if len(submap.params):
        with torch.no_grad():
            out = render(submap.params.detached(), viewmat_from_pose(kf.T_local_cam), cam)
            alpha = out.alpha.cpu().numpy()
    else:
        alpha = np.zeros_like(depth)
    s = cfg.seed_stride
    # A random offset per call so successive keyframes do not all sample the same pixel lattice.
    oy, ox = (int(x) for x in torch.randint(0, s, (2,), generator=generator))
    grid = np.zeros_like(depth, dtype=bool)
    grid[oy::s, ox::s] = True
    z_map = depth
    if cfg.seed_without_depth:
        z_map = np.where(depth > 0, depth, fallback_depth(depth, cfg.no_depth_min_region))
    cand = grid & (z_map > 0) & (alpha < cfg.alpha_seed)
    vs, us = np.nonzero(cand)
    if len(vs) > cfg.max_new_gaussians:
        pick = torch.randperm(len(vs), generator=generator)[: cfg.max_new_gaussians].numpy()
        vs, us = vs[pick], us[pick]
    if len(vs) == 0:
        return GaussianParams.empty()
    z = z_map[vs, us].astype(np.float64)
    pts_cam = np.stack([(us - cam.cx) / cam.fx * z, (vs - cam.cy) / cam.fy * z, z], axis=1)
    T = kf.T_local_cam
    pts = pts_cam @ T[:3, :3].T + T[:3, 3]
    radius = cfg.init_scale_factor * 0.5 * s * z / cam.fx
    rgb = unapply(f.color[vs, us].astype(np.float32) / 255.0, kf.exposure)  # in the map's colour gauge
    return GaussianParams.from_points(torch.as_tensor(pts, dtype=torch.float32), torch.as_tensor(rgb),
                                      torch.as_tensor(radius, dtype=torch.float32), cfg.init_opacity)


def fallback_depth(depth: np.ndarray, min_region: float = 0.01) -> np.ndarray:
    """[H, W] seeding depth for the large regions without valid depth (0 elsewhere): connected regions at least
    3 px across everywhere (thin lines along depth edges are left out) covering at least `min_region` of the image
    (a window, the sky, what lies beyond the sensor's range). Small holes in a measured surface are left to the
    Gaussians around them (on generated data, seeding them too cost 0.5 dB). A region's pixels get the farthest
    valid depth within max(3, W / 20) px, or, far inside it, the farthest valid depth of the frame: behind
    everything measured around it, where the colour the camera saw lies."""
    valid = depth > 0
    if valid.all() or not valid.any():
        return np.zeros_like(depth)
    k3 = np.ones((3, 3), np.uint8)
    opened = cv2.dilate(cv2.erode((~valid).astype(np.uint8), k3, borderType=cv2.BORDER_REPLICATE), k3)
    opened &= (~valid).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    big = np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= min_region * depth.size)[0] + 1
    if len(big) == 0:
        return np.zeros_like(depth)
    region = np.isin(labels, big)
    k = max(3, depth.shape[1] // 20) | 1
    near = cv2.dilate(np.where(valid, depth, 0).astype(np.float32), np.ones((k, k), np.uint8))
    z = np.where(near > 0, near, float(depth[valid].max()))
    return np.where(region, z, 0).astype(depth.dtype)


def make_optimizer(p: GaussianParams, cfg: MappingConfig, lr_scale: float = 1.0) -> torch.optim.Adam:
    """Adam over the five parameter groups with cfg's learning rates (times lr_scale). Uses torch's fused
    implementation (one kernel per group, no per-tensor Python loop) where the tensors' device has it."""
    groups = [
        {"params": [p.means], "lr": cfg.lr_means * lr_scale},
        {"params": [p.log_scales], "lr": cfg.lr_log_scales * lr_scale},
        {"params": [p.quats], "lr": cfg.lr_quats * lr_scale},
        {"params": [p.logit_opacities], "lr": cfg.lr_opacities * lr_scale},
        {"params": [p.colors], "lr": cfg.lr_colors * lr_scale},
    ]
    try:
        return torch.optim.Adam(groups, eps=1e-15, fused=True)
    except (RuntimeError, ValueError):  # a device / dtype without the fused kernel
        return torch.optim.Adam(groups, eps=1e-15)


def drop_non_finite(submap: Submap) -> int:
    """Remove the Gaussians with a NaN or Inf parameter (an optimisation that diverged, or a device that computes
    wrongly); returns how many. The caller warns and counts them."""
    p = submap.params
    with torch.no_grad():
        ok = torch.ones(len(p), dtype=torch.bool, device=p.means.device)
        for t in p.tensors():
            ok &= torch.isfinite(t.reshape(len(p), -1)).all(dim=1)
    bad = len(p) - int(ok.sum())
    if bad:
        submap.params = p.select(ok)
    return bad


class ExposureSteps:
    """The exposures of a set of views as leaves of one Adam (slam.dense.mapping.exposure), each regularised
    toward its anchor; views without a model, or fixed, render with theirs as constants."""

    def __init__(self, exposures: list, priors: list, fixed: list[bool], cfg: ExposureConfig | None):
        self.cfg = cfg
        self.values = [None if e is None else torch.as_tensor(np.asarray(e), dtype=torch.float32) for e in exposures]
        self.priors = [None if p is None else torch.as_tensor(np.asarray(p), dtype=torch.float32) for p in priors]
        self.leaves = {j: v.clone().requires_grad_(True) for j, v in enumerate(self.values)
                       if v is not None and not fixed[j] and cfg is not None}
        self.opt = torch.optim.Adam(list(self.leaves.values()), lr=cfg.lr) if self.leaves else None

    def color(self, j: int, out):
        """`out` (a render) with its colour as view j sees it."""
        e = self.leaves.get(j, self.values[j])
        return out if e is None else out._replace(color=apply(out.color, out.alpha, e))

    def penalty(self, j: int) -> torch.Tensor | float:
        leaf = self.leaves.get(j)
        if leaf is None or self.priors[j] is None or self.cfg.regulariser <= 0:
            return 0.0
        return self.cfg.regulariser * ((leaf - self.priors[j]) ** 2).sum()

    def zero_grad(self) -> None:
        if self.opt is not None:
            self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        if self.opt is not None:
            self.opt.step()

    def result(self, j: int) -> np.ndarray | None:
        e = self.leaves.get(j, self.values[j])
        return None if e is None else e.detach().double().numpy()


class Mapper:
    def __init__(self, cfg: MappingConfig, exposure: ExposureConfig | None = None):
        self.cfg = cfg
        self.exposure = exposure
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.non_finite_dropped = 0  # Gaussians removed for NaN / Inf parameters (metrics.json "warnings")

    def map(self, gmap: GaussianMap, submap: Submap, keyframes: list[MapKeyframe], iterations: int, *,
            stop: Callable[[int], bool] | None = None) -> MappingStats:
        """Seed from the newest keyframe (the last of `keyframes`), optimise (at most `iterations` steps; stop(i),
        if given, is asked before step i + 1 and ends the optimisation when true), prune.

        Guards: Gaussians with non-finite parameters are dropped with a warning (counted in `non_finite_dropped`);
        a new submap left without a Gaussian although its keyframe has valid depth raises SanityError, and so
        does a render of the newest keyframe with no alpha where its depth is valid (`optimise`)."""
        was_empty = len(submap.params) == 0
        new = seed_gaussians(submap, keyframes[-1], self.cfg, generator=self.gen)
        added = gmap.add(submap, new)
        first, last, it = self.optimise(submap, keyframes, iterations, stop=stop)
        bad = drop_non_finite(submap)
        if bad:
            self.non_finite_dropped += bad
            warnings.warn(f"submap {submap.id}: {bad} Gaussians had NaN or Inf parameters after mapping and were "
                          "removed", RuntimeWarning, stacklevel=2)
        pruned = gmap.prune(submap, min_opacity=self.cfg.prune_min_opacity, max_scale=self.cfg.prune_max_scale)
        if was_empty and len(submap.params) == 0 and bool((keyframes[-1].rgbd.depth > 0).any()):
            raise SanityError(f"mapping left the new submap {submap.id} without a Gaussian although its keyframe "
                              f"has valid depth ({added} seeded, {bad} non-finite, {pruned} pruned); the kernel "
                              "device computes wrongly? (swarmsplat devices runs its self-check)")
        return MappingStats(added, pruned, it, first, last)

    def optimise(self, submap: Submap, keyframes: list[MapKeyframe], iterations: int, *,
                 stop: Callable[[int], bool] | None = None) -> tuple[float, float, int]:
        """Adam on all Gaussians of `submap` for `iterations` steps (fewer when stop(steps done) turns true), each
        on one keyframe: the newest with probability `current_keyframe_fraction`, otherwise one drawn uniformly
        from the submap's keyframes. Returns (first loss, mean loss of the last 5 steps, steps done)."""
        cfg = self.cfg
        if iterations <= 0 or len(submap.params) == 0:
            return float("nan"), float("nan"), 0
        p = submap.params.detached().requires_grad_(True)
        opt = make_optimizer(p, cfg)
        ex = ExposureSteps([k.exposure for k in keyframes], [k.exposure_prior for k in keyframes],
                           [k.exposure_fixed for k in keyframes], self.exposure)
        targets = [(viewmat_from_pose(k.T_local_cam), k.rgbd.color_tensor(), k.rgbd.depth_tensor(), k.rgbd.camera)
                   for k in keyframes]
        losses = []
        newest = len(targets) - 1
        checked = False
        for i in range(iterations):
            if stop is not None and stop(i):
                break
            if len(targets) == 1 or float(torch.rand(1, generator=self.gen)) < cfg.current_keyframe_fraction:
                j = len(targets) - 1
            else:
                j = int(torch.randint(0, len(targets), (1,), generator=self.gen))
            vm, color, depth, cam = targets[j]
            opt.zero_grad(set_to_none=True)
            ex.zero_grad()
            act = activate(p)
            out = render(p, vm, cam, activated=act)
            if j == newest and not checked:
                _check_alpha(out.alpha, depth, submap.id)
                checked = True
            lambda_color = 0.0 if keyframes[j].exposure_outlier else cfg.lambda_color
            loss = mapping_loss(ex.color(j, out), color, depth, p, cfg, lambda_color, cfg.isotropic_regulariser, act)
            loss = loss + ex.penalty(j)
            loss.backward()
            opt.step()
            ex.step()
            losses.append(float(loss.detach()))
        submap.params = p.detached()
        for j, k in enumerate(keyframes):  # each keyframe's exposure array, updated in place (it is the Keyframe's)
            e = ex.result(j)
            if e is not None and k.exposure is not None and not k.exposure_fixed:
                k.exposure[:] = e
        if not losses:
            return float("nan"), float("nan"), 0
        return losses[0], float(np.mean(losses[-5:])), len(losses)


def _check_alpha(alpha: torch.Tensor, depth: torch.Tensor, submap_id: int) -> None:
    """The newest keyframe was just seeded (or was already covered): a render of it with no alpha at all where its
    depth is valid cannot be right."""
    with torch.no_grad():
        valid = depth > 0
        if bool(valid.any()) and not bool((alpha.detach()[valid] > 0).any()):
            raise SanityError(f"submap {submap_id}: the render of its newest keyframe is empty (alpha 0) wherever "
                              "the keyframe has valid depth; the kernel device computes wrongly? (swarmsplat devices "
                              "runs its self-check)")
