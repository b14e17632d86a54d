"""Two-stage tracking (GRAND-SLAM §III-C): coarse frame-to-frame hybrid RGB-D odometry (eq. 4), then
frame-to-model refinement against the active submap with the Gaussians frozen.

Refinement (tracking.refine, on by default), `method: gauss_newton` (default): the submap is rendered through
the rasteriser once per map update, at the pose of the frame that was just mapped (the keyframe), as an RGB-D
"model view": composited colour and alpha-weighted depth D̂ = Σ z α T, exactly the quantities eq. 3 fits to the
input, kept where alpha >= `alpha_min`; slam.dense.tracking.model_align prepares its vertices / normals / intensity once
(ModelTarget). Every following frame is aligned to that view by Gauss-Newton on the hybrid point-to-plane +
intensity residuals at `refine_max_width`, starting from the coarse pose. The twist is applied on the left in the
view's camera frame (rotation about the camera, not the submap origin).

With `debias_view` (on by default) the view is placed where its own keyframe aligns to it, so a map that sits a
few millimetres off its keyframe does not pull every later frame by that offset, which chained from keyframe to
keyframe and made plain refinement worse than coarse-only on generated data. Measured with perf.tracking_refine
(loop closure off, README "Frame-to-model refinement"): Redwood 211 10.08 vs 10.25 mm coarse-only at 1.40x the
coarse tracking time; the demo's three agents 6.3 / 2.8 / 5.5 vs 7.4 / 8.0 / 6.0 mm at 1.24-1.28x. A per-frame
acceptance test keeps the coarse pose unless the refinement lowers the robust residual against the view. In
real-time mode a frame may come with a deadline (Tracker.deadline): when the refinement's median time would pass
it and the coarse stage passed its checks without a recovery, the coarse pose goes out instead (counted; never
two frames in a row).

`method: adam` is the paper's literal eq. 5: Adam on a twist xi = [omega, v] applied on the left of the
world(local)-to-camera matrix, viewmat = exp(xi) @ viewmat0, through the rasteriser's pose gradient, separate step
sizes for rotation and translation, over a small pyramid. Measured (README), refining each of 30 Redwood frames
from its coarse pose: mean position error 8.7 mm with depth / alpha, 5.0 mm without, vs 4.5 mm coarse, at
~6 s per frame (Gauss-Newton: 0.2-0.5 s) on the loaded machine.

Why the model view uses D̂ and not D̂ / alpha: mapping fits D̂ (not D̂ / alpha) to the input depth, so where
alpha < 1 the normalised depth lies behind the surface by (1/alpha - 1) x depth; on Redwood mapped at 160 px
(alpha 0.992 at 2 m) that is +13.5 mm median, and refining against it pulled every pose ~15 mm forward. D̂ is
only right once mapping has fitted it: with mapping.init_scale_factor 1 at 320 px the map stays translucent
(median alpha 0.953, D̂ 74 mm short after the first keyframe) and the registration fails; with 2 (the
default) alpha is 0.996 and D̂ within 0.2 mm.
"""

from __future__ import annotations

import collections
import statistics
import time
from dataclasses import dataclass

import numpy as np
import torch

from swarmsplat.kernels import se3

from swarmsplat.slam.config import TrackingConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from .model_align import ModelTarget, Residual, align_to_model
from .recovery import RecoveryCounts, coarse_passes, recover
from swarmsplat.slam.dense.rgbd_registration import Registration, coarse_odometry, pyramid
from swarmsplat.slam.dense.render import render, rgbd_loss


@dataclass
class TrackResult:
    T_local_cam: np.ndarray  # [4, 4] refined pose in the active submap's frame
    T_local_cam_coarse: np.ndarray  # [4, 4] after the coarse stage
    coarse_ok: bool
    iterations: int
    loss: float
    coarse: Registration | None = None  # the coarse stage's registration (its information feeds the pose graph)
    refine: "RefineInfo | None" = None  # what the Gauss-Newton refinement did (None when it did not run)
    recovered: str = ""  # "retry" | "relocalised" when the coarse stage failed and recovery placed the frame


@dataclass
class RefineInfo:
    """One frame's Gauss-Newton refinement: whether its pose was kept, why not, and the evidence."""

    accepted: bool
    reason: str  # "ok" | "coverage" | "failed" | "max_correction" | "residual" | "inliers"
    coverage: float  # fraction of the model view with alpha >= alpha_min
    iterations: int = 0
    correction_m: float = float("nan")  # refined vs coarse pose
    correction_deg: float = float("nan")
    start: Residual | None = None  # objective at the coarse pose (finest level)
    final: Residual | None = None  # ... at the refined pose
    rmse: float = float("nan")

    @property
    def score_ratio(self) -> float:
        """Refined over coarse robust cost per source point (< 1: the refinement lowered the objective)."""
        if self.start is None or self.final is None:
            return float("nan")
        return self.final.score / max(self.start.score, 1e-300)


def model_view(params: GaussianParams, T_local_cam: np.ndarray, camera, *, alpha_min: float,
               exposure: np.ndarray | None = None) -> RGBD:
    """The submap `params` seen from T_local_cam [4, 4] (camera-to-local) through `camera`, as an RGB-D frame:
    composited colour (uint8; as a camera of `exposure` sees it, slam.dense.mapping.exposure) and alpha-weighted
    depth D̂ (metres), depth 0 where alpha < alpha_min."""
    from swarmsplat.slam.dense.mapping.exposure import apply

    with torch.no_grad():
        out = render(params, torch.as_tensor(se3.inverse(T_local_cam), dtype=torch.float32), camera)
        c = apply(out.color, out.alpha, exposure)
    color = (c.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    depth = torch.where(out.alpha >= alpha_min, out.depth, torch.zeros_like(out.depth))
    return RGBD(color, depth.cpu().numpy().astype(np.float32), camera)


def refine_strides(cfg: TrackingConfig) -> list[int]:
    """Strides of the refinement pyramid at refine_max_width, coarsest first (pyramid_levels 2 -> [2, 1])."""
    return [1 << k for k in reversed(range(cfg.pyramid_levels))]


def refine_against_view(frame: RGBD, view: RGBD, T_local_view: np.ndarray, T_local_cam: np.ndarray,
                        cfg: TrackingConfig, *, max_depth: float = 10.0,
                        target: ModelTarget | None = None) -> tuple[np.ndarray, int, float]:
    """Gauss-Newton alignment of `frame` to a model view rendered at T_local_view, from the pose T_local_cam
    (slam.dense.tracking.model_align; `target` is the view prepared by ModelTarget, built here when None).
    Returns (pose, iterations, point-to-plane RMS residual in metres); the input pose with 0 iterations when
    `refine_detail` does not accept the refinement."""
    T, info = refine_detail(frame, view, T_local_view, T_local_cam, cfg, max_depth=max_depth, target=target)
    return (T, info.iterations, info.rmse) if info.accepted else (T_local_cam, 0, float("nan"))


def refine_detail(frame: RGBD, view: RGBD, T_local_view: np.ndarray, T_local_cam: np.ndarray,
                  cfg: TrackingConfig, *, max_depth: float = 10.0, target: ModelTarget | None = None,
                  pyramid=None) -> tuple[np.ndarray, RefineInfo]:
    """`refine_against_view` with its evidence. The refined pose is accepted only when the view covers at least
    `min_model_coverage` of the image, the alignment succeeds, it moves the pose by at most `max_correction`, and
    (the per-frame acceptance test) it lowers the robust hybrid objective against the view by at least
    `min_residual_gain` of its value at the coarse pose without losing more than `max_inlier_loss` of the
    correspondences. Returns (pose, info): the coarse pose when not accepted. `pyramid`: the frame's
    FramePyramid at refine_max_width (slam.dense.rgbd_registration.pyramid), shared with the coarse stage."""
    f = frame.resized(cfg.refine_max_width)
    cov = view.valid_fraction()
    if cov < cfg.min_model_coverage:
        return T_local_cam, RefineInfo(False, "coverage", cov)
    target = target or ModelTarget(view, refine_strides(cfg), max_depth=max_depth)
    r = align_to_model(f, target, se3.inverse(T_local_view) @ T_local_cam, iterations=cfg.iterations,
                       photometric_weight=cfg.photometric_weight, max_distance=cfg.max_distance, max_depth=max_depth,
                       tolerance=cfg.step_tolerance, evaluate_final=cfg.acceptance_test, pyramid=pyramid)
    info = RefineInfo(False, "failed", cov, r.iterations, start=r.start, final=r.final, rmse=r.rmse)
    if not r.success:
        return T_local_cam, info
    # Projected onto SE(3): `se3.inverse` is a transpose, so any drift of a stored pose off SE(3) comes back as
    # a scale error, and refining against a view whose pose is itself a refined one multiplied that error by ~3
    # per keyframe (measured on Redwood 211: |R^T R - I| 1e-14 at frame 9, 7e-2 by frame 87, where frames stepped
    # twice the true motion).
    T = se3.project_rigid(T_local_view @ r.T_view_cam)
    D = se3.inverse(T_local_cam) @ T
    info.correction_m = float(np.linalg.norm(D[:3, 3]))
    info.correction_deg = float(np.degrees(se3.rotation_angle(D[:3, :3])))
    if info.correction_m > cfg.max_correction:
        info.reason = "max_correction"
        return T_local_cam, info
    if cfg.acceptance_test and r.start is not None and r.final is not None:
        if not info.score_ratio <= 1.0 - cfg.min_residual_gain:
            info.reason = "residual"
            return T_local_cam, info
        if r.final.count < (1.0 - cfg.max_inlier_loss) * r.start.count:
            info.reason = "inliers"
            return T_local_cam, info
    info.accepted, info.reason = True, "ok"
    return T, info


def refine_pose(params: GaussianParams, frame: RGBD, T_local_cam: np.ndarray, cfg: TrackingConfig,
                *, max_depth: float = 10.0) -> tuple[np.ndarray, int, float]:
    """Frame-to-model refinement of T_local_cam [4, 4] against `params` with cfg.method, the model rendered at
    T_local_cam itself (the Tracker renders it once per map update instead). Returns (pose, iterations, loss)."""
    if cfg.method == "gauss_newton":
        cam = frame.resized(cfg.refine_max_width).camera
        view = model_view(params.detached(), T_local_cam, cam, alpha_min=cfg.alpha_min)
        return refine_against_view(frame, view, T_local_cam, T_local_cam, cfg, max_depth=max_depth)
    return refine_pose_adam(params, frame, T_local_cam, cfg)


def refine_pose_adam(params: GaussianParams, frame: RGBD, T_local_cam: np.ndarray, cfg: TrackingConfig
                     ) -> tuple[np.ndarray, int, float]:
    """Eq. 5 by Adam over a resolution pyramid (coarsest first). Returns (pose, iterations, loss)."""
    frozen = params.detached()
    T_start = T = np.asarray(T_local_cam, dtype=np.float64)
    total_it, loss = 0, float("nan")
    for level in reversed(range(cfg.pyramid_levels)):
        f = frame.resized(max(16, cfg.refine_max_width >> level))
        iters = cfg.adam_iterations if level == 0 else max(1, cfg.adam_iterations // 2)
        T, it, loss = _refine_level(frozen, f, T, cfg, iters)
        total_it += it
    if cfg.min_relative_gain > 0 and np.isfinite(loss):
        loss0 = tracking_loss(frozen, frame.resized(cfg.refine_max_width), T_start, cfg)
        if not loss < (1.0 - cfg.min_relative_gain) * loss0:
            return T_start, total_it, loss0
    return T, total_it, loss


def tracking_loss(params: GaussianParams, f: RGBD, T_local_cam: np.ndarray, cfg: TrackingConfig) -> float:
    """The eq.-5 tracking loss of `f` rendered at T_local_cam (no gradient)."""
    with torch.no_grad():
        out = render(params, torch.as_tensor(se3.inverse(T_local_cam), dtype=torch.float32), f.camera)
        if float(out.alpha.max()) < cfg.alpha_min:
            return float("inf")
        return float(rgbd_loss(out, f.color_tensor(), f.depth_tensor(), lambda_color=cfg.lambda_color,
                               alpha_power=cfg.alpha_power, alpha_min=cfg.alpha_min, inlier_k=cfg.inlier_k,
                               normalise=cfg.normalise_by_alpha))


def _refine_level(params: GaussianParams, f: RGBD, T0: np.ndarray, cfg: TrackingConfig, iters: int
                  ) -> tuple[np.ndarray, int, float]:
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
        out = render(params, viewmat.float(), f.camera)
        if float(out.alpha.detach().max()) < cfg.alpha_min:
            break  # nothing of the model is visible: keep the coarse pose
        loss = rgbd_loss(out, color, depth, lambda_color=cfg.lambda_color, alpha_power=cfg.alpha_power,
                         alpha_min=cfg.alpha_min, inlier_k=cfg.inlier_k, normalise=cfg.normalise_by_alpha)
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


MAX_GAP_RATIO = 4.0  # motion_prior extrapolates the last step at most this many times its span


class Tracker:
    """Keeps the previous frame for the coarse stage and a constant-velocity fallback."""

    exposure: np.ndarray | None = None  # (set per instance; the class default serves trackers pickled before it)
    _gap = 1.0  # (likewise)

    def __init__(self, cfg: TrackingConfig, *, max_depth: float = 10.0):
        self.cfg = cfg
        self.max_depth = max_depth
        self._prev: RGBD | None = None
        self._prev_pyramid = None  # its levels for the coarse stage (rgbd_registration.pyramid)
        self._prev_pose: np.ndarray | None = None  # T_local_cam of the previous frame (active submap frame)
        self._velocity = np.eye(4)  # T_prev_cur of the last step
        self._gap = 1.0  # frames the last step spanned (frames dropped or skipped before it: more than 1)
        # (params it shows, T_local_view, view, its ModelTarget)
        self._view: tuple[GaussianParams, np.ndarray, RGBD, ModelTarget] | None = None
        self.view_biases: list[float | None] = []  # per rendered view: |translation| of its keyframe's self-check
        # the current submap's keyframes (at coarse_max_width, T_local_cam) for re-localisation, oldest first
        self._anchors: list[tuple[RGBD, np.ndarray]] = []
        self._anchor_params: GaussianParams | None = None
        self.recoveries = RecoveryCounts()
        # A time.monotonic() value by which the pose is due (slam.run.realtime sets it per frame; None offline):
        # the refinement is left out when its expected time would pass it.
        self.deadline: float | None = None
        self.refines_skipped = 0  # frames posed without the refinement for the deadline
        self._refine_s: collections.deque[float] = collections.deque(maxlen=20)  # s, the last refinements
        self._skipped_last = False
        # the exposure of the keyframe the model view is rendered for (slam.dense.mapping.exposure; None: no
        # model): frames are aligned to the map as that camera saw it, not to the map's own colours
        self.exposure: np.ndarray | None = None

    def reset_frame(self, T_new_old: np.ndarray) -> None:
        """Re-express the stored previous pose after the active submap's frame changes (new submap)."""
        if self._prev_pose is not None:
            self._prev_pose = np.asarray(T_new_old) @ self._prev_pose
        self._view = None
        self._anchors = []  # a new submap: its first keyframe is added once it is mapped

    def motion_prior(self, gap: float = 1.0) -> np.ndarray:
        """T_prev_cur expected for a frame `gap` frames after the previous one: the last step's motion scaled by
        `gap` over the frames that step spanned (constant velocity in time, on SE(3)), so a frame after dropped or
        skipped ones starts as far along as the camera went meanwhile. The scale is capped at MAX_GAP_RATIO."""
        ratio = min(float(gap) / self._gap, MAX_GAP_RATIO)
        if ratio == 1.0:
            return self._velocity
        return se3.exp(se3.log(self._velocity) * ratio)

    def track(self, frame: RGBD, params: GaussianParams, *, gap: float = 1.0) -> TrackResult:
        """Pose of `frame` in the active submap's local frame. gap: how many frames it comes after the previous
        tracked one (1 offline; more after frames dropped in real time or skipped): the constant-velocity start
        is scaled to it (`motion_prior`)."""
        if self._prev is None:
            T = np.eye(4)
            self._remember(frame, T)
            return TrackResult(T, T, True, 0, 0.0)
        if len(params) and params is not self._anchor_params:  # a map update: the previous frame was its keyframe
            self._anchor_params = params
            self._anchors.append((self._prev, self._prev_pose.copy()))
        coarse_ok, r, recovered = False, None, ""
        prior = self.motion_prior(gap)
        T_coarse = self._prev_pose @ prior
        src = frame.resized(self.cfg.coarse_max_width)
        src_pyramid = pyramid(src)  # levels computed on first use, kept for the next frame's coarse stage
        if self.cfg.coarse == "rgbd_odometry":
            tgt = self._prev.resized(self.cfg.coarse_max_width)
            levels = self._prev_pyramid if tgt is self._prev else pyramid(tgt)
            r = coarse_odometry(src, tgt, prior, max_depth=self.max_depth, pyramids=(src_pyramid, levels),
                                eval_stride=max(1, src.camera.width // self.cfg.coarse_eval_max_width))
            coarse_ok = coarse_passes(r, self.cfg)
            if coarse_ok:
                T_coarse = self._prev_pose @ r.T_target_source
            else:
                self.recoveries.coarse_failed += 1
            if not coarse_ok and self.cfg.recovery:
                found = recover(src, tgt, self._prev_pose, self._anchors, self.cfg, self.recoveries,
                                max_depth=self.max_depth)
                if found is not None:
                    T_coarse, r, recovered = found
                    coarse_ok = r is not None
        T, it, loss, info = T_coarse, 0, float("nan"), None
        refine = ((self.cfg.refine or (self.cfg.refine_on_coarse_failure and not coarse_ok))
                  and self.cfg.iterations > 0 and len(params) > 0)
        if refine and coarse_ok and not recovered and self._past_deadline():  # a doubtful coarse pose is refined
            refine = False
        if refine:
            t0 = time.monotonic()
            if self.cfg.method == "gauss_newton":
                T_view, view = self._model_view(params, frame)
                share = self.cfg.refine_max_width == self.cfg.coarse_max_width
                T, info = refine_detail(frame, view, T_view, T_coarse, self.cfg, max_depth=self.max_depth,
                                        target=self._view[3], pyramid=src_pyramid if share else None)
                it, loss = (info.iterations, info.rmse) if info.accepted else (0, float("nan"))
            else:
                T, it, loss = refine_pose_adam(params, frame, T_coarse, self.cfg)
            self._refine_s.append(time.monotonic() - t0)
        self._velocity = se3.inverse(self._prev_pose) @ T
        self._gap = max(float(gap), 1.0)
        self._remember(frame, T, src, src_pyramid)
        return TrackResult(T, T_coarse, coarse_ok, it, loss, r, info, recovered)

    def _past_deadline(self) -> bool:
        """Whether the refinement, taking the median of its last runs, would end after `deadline` (then it is
        left out and counted: the coarse pose, which passed its own checks, goes out in time). Never twice in a
        row: the frame after a skipped one refines, so the estimate stays measured (a first run slowed by loading
        its kernels would otherwise leave every later refinement out)."""
        late = (self.deadline is not None and bool(self._refine_s) and not self._skipped_last
                and time.monotonic() + statistics.median(self._refine_s) > self.deadline)
        self._skipped_last = late
        self.refines_skipped += late
        return late

    def _model_view(self, params: GaussianParams, frame: RGBD) -> tuple[np.ndarray, RGBD]:
        return self.view_of(params, frame.resized(self.cfg.refine_max_width).camera)

    def view_of(self, params: GaussianParams, camera) -> tuple[np.ndarray, RGBD]:
        """(T_local_view [4, 4], model view) the refinement aligns to: rendered again only after the map changed
        (mapping replaces `params`), at the pose of the frame tracked last: the keyframe that was just mapped.
        With `debias_view` the returned pose is where that keyframe aligns to the view (its self-check below),
        so a view offset from its keyframe by B gives T_local_view = T_keyframe @ inv(B)."""
        if self._view is None or self._view[0] is not params:
            self._view = self.build_view(params, camera, self._prev, self._prev_pose, self.exposure)
        return self._view[1], self._view[2]

    def build_view(self, params: GaussianParams, camera, keyframe: RGBD, T_local_kf: np.ndarray,
                   exposure: np.ndarray | None = None) -> tuple:
        """The model view of `params` rendered through `camera` at T_local_kf [4, 4], the pose of the keyframe
        `keyframe` it was mapped from, checked (and with `debias_view` placed) by that keyframe's own alignment to
        it: (params, T_local_view, view, its ModelTarget), what `view_of` keeps. Reads only the configuration
        (slam.run.realtime builds views on its mapping thread and hands them over with `use_view`). `exposure`:
        the keyframe's (slam.dense.mapping.exposure), so the view shows the map as that camera saw it."""
        view = model_view(params.detached(), T_local_kf, camera, alpha_min=self.cfg.alpha_min, exposure=exposure)
        target = ModelTarget(view, refine_strides(self.cfg), max_depth=self.max_depth)
        B = self._view_bias(view, target, keyframe)
        T_view = T_local_kf.copy()
        self.view_biases.append(None if B is None else float(np.linalg.norm(B[:3, 3])))
        if B is None or float(np.linalg.norm(B[:3, 3])) > self.cfg.max_view_bias:
            view = RGBD(view.color, np.zeros_like(view.depth), view.camera)  # unusable: covers nothing
        elif self.cfg.debias_view:
            T_view = se3.project_rigid(T_view @ se3.inverse(B))
        return params, T_view, view, target

    def use_view(self, built: tuple, keyframe: RGBD, T_local_kf: np.ndarray) -> None:
        """Track the next frames against a view `build_view` made of a newer map (mapped from `keyframe` at
        T_local_kf, in the active submap), which also joins the re-localisation anchors."""
        params = built[0]
        if len(params) and params is not self._anchor_params:
            self._anchor_params = params
            self._anchors.append((keyframe.resized(self.cfg.coarse_max_width), np.array(T_local_kf, copy=True)))
        self._view = built

    def _view_agrees(self, view: RGBD, target: ModelTarget) -> bool:
        """Self-check of a fresh model view: the keyframe it was rendered at, aligned to it from its own pose,
        must stay within `max_view_bias` (m). A map that disagrees with its own keyframe (e.g. too few mapping
        iterations) would pull every frame by that much."""
        B = self._view_bias(view, target)
        return B is not None and float(np.linalg.norm(B[:3, 3])) <= self.cfg.max_view_bias

    def _view_bias(self, view: RGBD, target: ModelTarget, keyframe: RGBD | None = None) -> np.ndarray | None:
        """T_view_keyframe [4, 4]: the keyframe the view was rendered at (default: the frame tracked last),
        aligned to it from its own pose (the identity for a map that agrees with its keyframe); None when the
        alignment fails."""
        f = (self._prev if keyframe is None else keyframe).resized(self.cfg.refine_max_width)
        if f.camera != view.camera or view.valid_fraction() < self.cfg.min_model_coverage:
            return np.eye(4)  # nothing to check against (refine_against_view skips an uncovered view itself)
        r = align_to_model(f, target, np.eye(4), iterations=self.cfg.iterations,
                           photometric_weight=self.cfg.photometric_weight, max_distance=self.cfg.max_distance,
                           max_depth=self.max_depth)
        return r.T_view_cam if r.success else None

    def _remember(self, frame: RGBD, T: np.ndarray, small: RGBD | None = None, levels=None) -> None:
        """Keep `frame` (`small`: it at coarse_max_width, with its pyramid `levels`) and its pose T [4, 4]."""
        self._prev = small if small is not None else frame.resized(self.cfg.coarse_max_width)
        self._prev_pyramid = levels if small is not None else pyramid(self._prev)
        self._prev_pose = se3.project_rigid(T)  # the base of every later pose and model view: kept rigid
