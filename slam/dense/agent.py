"""One GRAND-SLAM agent. `Agent.step` reads as the algorithm: track, maybe start a submap, map, detect loops."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.memory import trim_heap

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.loops.edge_information import OdometryChain, failed_covariance, registration_covariance
from .frames import RGBD, make_rgbd
from .gaussian_map import GaussianMap, GaussianParams
from swarmsplat.slam.dense.loops.loop_closure import LoopCloser
from swarmsplat.slam.dense.mapping import exposure
from swarmsplat.slam.dense.mapping.mapper import MapKeyframe, Mapper, MappingStats
from .render import render, viewmat_from_pose
from .submap_codec import use_storage
from .submaps import (Keyframe, follow_keyframe_optimum, frame_local_poses, needs_new_submap, start_submap,
                      world_pose)
from swarmsplat.slam.dense.tracking.tracker import Tracker


@dataclass
class FramePose:
    frame_index: int
    timestamp: float
    submap_id: int
    T_local_cam: np.ndarray  # [4, 4] in its submap's frame


@dataclass
class Timings:
    tracking: float = 0.0
    mapping: float = 0.0
    loop_closure: float = 0.0
    frames: int = 0
    skipped: list[int] = field(default_factory=list)  # frame indices, in input order
    skip_reasons: dict[int, str] = field(default_factory=dict)  # frame index -> why it was skipped


class Agent:
    def __init__(self, camera: PinholeCamera, cfg: SlamConfig | None = None, *, name: str = "agent"):
        self.cfg = cfg or SlamConfig()
        self.name = name
        self.camera = camera
        self.gmap = GaussianMap()
        use_storage(self.gmap, self.cfg.submaps.storage)  # in memory; a driver with a run folder may offload
        self.tracker = Tracker(self.cfg.tracking, max_depth=self.cfg.image.max_depth)
        # the camera's exposure model (slam.dense.mapping.exposure) is on from the start with exposure.enabled true;
        # with "auto" it is switched on by the first keyframe whose fit shows the camera's exposure change
        self.exposure_active = self.cfg.exposure.enabled is True
        self.exposure_from: int | None = 0 if self.exposure_active else None  # the keyframe that switched it on
        self.mapper = Mapper(self.cfg.mapping, self.cfg.exposure if self.exposure_active else None)
        self.loops = LoopCloser(self.cfg.loop_closure, max_depth=self.cfg.image.max_depth)
        self._chain = OdometryChain(self.loops.model)  # tracking covariance since the last keyframe
        self.keyframes: list[Keyframe] = []
        # Frames the map refinement fits beside the keyframes but mapping never saw (a real-time run's deferred
        # keyframes: slam.run.realtime.agent, config runtime.late_views); negative ids, in no submap's keyframe list.
        self.late_views: list[Keyframe] = []
        self.poses: list[FramePose] = []
        self.time = Timings()
        self._last_kf_pose: np.ndarray | None = None  # T_local_cam of the last keyframe (active submap)
        # Keep every keyframe's mapping-resolution images after its submap is retired (a team sets this when its
        # server refines the merged map on them: config map_refine.views "mapping").
        self.keep_keyframe_images = False
        # Pack retired submaps' keyframe images losslessly (slam.dense.packed): identical reads, a fraction of
        # the memory.
        self.compress_keyframes = True
        # Where retired keyframes' packed images go out of memory (slam.io.submap_files.KeyframeFiles; a driver
        # with a run folder sets it: config submaps.offload_keyframes); None keeps them in memory.
        self.frame_store = None

    def __setstate__(self, state: dict) -> None:  # checkpoints of agents from before the keyframe store
        state.setdefault("frame_store", None)
        state.setdefault("late_views", [])
        state.setdefault("exposure_active", state["cfg"].exposure.enabled is True)
        state.setdefault("exposure_from", 0 if state["exposure_active"] else None)
        self.__dict__.update(state)

    # ---- the algorithm ----------------------------------------------------------------------------------------

    def step(self, index: int, timestamp: float, color: np.ndarray, depth: np.ndarray | None) -> FramePose | None:
        """Process one RGB-D frame; returns its pose record, or None when the frame was skipped."""
        frame = self._prepare(index, color, depth)
        if frame is None:
            return None
        t0 = time.perf_counter()
        T_local_cam = self._track(frame, index)
        t1 = time.perf_counter()
        if self._is_keyframe(T_local_cam):
            n_submaps = len(self.gmap.submaps)
            T_local_cam = self._maybe_start_submap(T_local_cam)
            kf = self._add_keyframe(index, timestamp, frame, T_local_cam)
            self._map(kf)
            self.tracker.exposure = kf.exposure  # the next frames are aligned to the map as this camera saw it
            t2 = time.perf_counter()
            self._detect_loops(kf)
            self.time.mapping += t2 - t1
            self.time.loop_closure += time.perf_counter() - t2
            if n_submaps and len(self.gmap.submaps) > n_submaps and self.cfg.kernels.malloc_trim:
                trim_heap()  # a submap was finished: its memory is free now (kernels.malloc_trim)
        self.time.tracking += t1 - t0
        self.time.frames += 1
        rec = FramePose(index, timestamp, self.gmap.active.id, T_local_cam)
        self.poses.append(rec)
        return rec

    # ---- the steps ------------------------------------------------------------------------------------------

    def _prepare(self, index: int, color: np.ndarray, depth: np.ndarray | None) -> RGBD | None:
        img = self.cfg.image
        f = make_rgbd(color, depth, self.camera, min_depth=img.min_depth, max_depth=img.max_depth)
        if f.valid_fraction() < img.min_valid_fraction:
            self.skip_frame(index, f"only {100 * f.valid_fraction():.1f}% of its depth is valid (need "
                                   f"{100 * img.min_valid_fraction:.0f}%)")
            return None
        return f.resized(img.max_width)

    def skip_frame(self, index: int, reason: str) -> None:
        """Leave frame `index` out (too little valid depth, or unreadable: slam.run.guard.read_frame) with one
        warning; it is listed with `reason` in metrics.json `skipped_frames`."""
        warnings.warn(f"{self.name}: frame {index} skipped: {reason}", RuntimeWarning, stacklevel=4)
        self.time.skipped.append(int(index))
        self.time.skip_reasons[int(index)] = reason

    def skipped_frames(self) -> list[dict]:
        """[{"frame": index, "reason": why}] of every skipped frame, in input order (metrics.json)."""
        return [{"frame": i, "reason": self.time.skip_reasons.get(i, "")} for i in self.time.skipped]

    def _tracking_params(self) -> GaussianParams:
        """The Gaussians the tracker aligns to: the active submap's (slam.run.realtime: the last ones mapping
        finished, while it works on the next)."""
        return self.gmap.active.params if self.gmap.submaps else GaussianParams.empty()

    def _track(self, frame: RGBD, index: int | None = None) -> np.ndarray:
        # frames since the previous tracked one (dropped in real time, or skipped): the tracker's motion prior
        gap = index - self.poses[-1].frame_index if index is not None and self.poses else 1
        r = self.tracker.track(frame, self._tracking_params(), gap=max(1, gap))
        if self.poses and self.poses[-1].submap_id == self.gmap.active.id:
            step = se3.inverse(self.poses[-1].T_local_cam) @ r.T_local_cam
            c = r.coarse
            cov = (registration_covariance(c.information, c.n_correspondences, c.inlier_rmse, c.T_target_source,
                                           self._chain.model)
                   if r.coarse_ok and c is not None else failed_covariance(self._chain.model))
            self._chain.add(step, cov)
        return r.T_local_cam

    def _is_keyframe(self, T_local_cam: np.ndarray) -> bool:
        k = self.cfg.keyframes
        if self._last_kf_pose is None or not self.poses:
            return True
        since = self.poses[-1].frame_index - self.keyframes[-1].frame_index + 1
        D = se3.inverse(self._last_kf_pose) @ T_local_cam
        return (since >= k.every or np.linalg.norm(D[:3, 3]) > k.max_translation
                or np.degrees(se3.rotation_angle(D[:3, :3])) > k.max_rotation_deg)

    def _maybe_start_submap(self, T_local_cam: np.ndarray) -> np.ndarray:
        """Start a new submap at this keyframe if needed; returns the frame's pose in the (new) active submap."""
        if self.gmap.submaps and not needs_new_submap(self.cfg.submaps, T_local_cam, len(self.gmap.active.keyframe_ids)):
            return T_local_cam
        T_world_cam = self.gmap.active.T_world_local @ T_local_cam if self.gmap.submaps else np.eye(4)
        start_submap(self.gmap, T_world_cam, self.keyframes, keep_images=self.keep_keyframe_images,
                     compress=self.compress_keyframes,
                     prune_min_contribution=self.cfg.submaps.prune_min_contribution,
                     frame_store=self.frame_store)
        self.tracker.reset_frame(se3.inverse(T_local_cam))
        return np.eye(4)

    def _add_keyframe(self, index: int, timestamp: float, frame: RGBD, T_local_cam: np.ndarray, *,
                      exposure_now: bool = True) -> Keyframe:
        """Add the keyframe to the active submap, with its exposure fitted (`_keyframe_exposure`) unless
        `exposure_now` is False: the real-time agent fits it on its mapping worker, off the tracker's time."""
        s = self.gmap.active
        kf = Keyframe(len(self.keyframes), index, timestamp, s.id, T_local_cam.copy(),
                      frame.resized(self.cfg.mapping.max_width), frame.resized(self.cfg.submaps.keep_keyframe_width))
        self.keyframes.append(kf)
        s.keyframe_ids.append(kf.id)
        self._last_kf_pose = T_local_cam.copy()
        if exposure_now:
            self._keyframe_exposure(kf)
        return kf

    def _keyframe_exposure(self, kf: Keyframe) -> None:
        """kf's exposure (slam.dense.mapping.exposure), from the map as it stands before kf is mapped: fitted when
        the model is on; with exposure.enabled "auto", watched for the change that switches it on."""
        first = self.gmap.submaps[kf.submap_id].keyframe_ids[0] == kf.id
        if self.exposure_active:
            self._fit_exposure(kf, first_of_submap=first)
        elif self.cfg.exposure.enabled == "auto" and kf.id > 0:
            self._watch_exposure(kf, first_of_submap=first)

    def _watch_exposure(self, kf: Keyframe, *, first_of_submap: bool) -> None:
        """exposure.enabled "auto": fit kf's exposure against the map and switch the model on when its gain departs
        from the map's colours by more than exposure.auto_threshold in any channel (a fit from a black or white
        frame does not count). The keyframes before it keep the identity: their fits stayed within the threshold,
        so the map's colours are theirs."""
        fitted = self._exposure_fit(kf, first_of_submap)
        if fitted is None or exposure.is_outlier(fitted.exposure, exposure.identity(), self.cfg.exposure.max_gain):
            return
        # Against the map's own error: the previous keyframe fitted to the submap it was mapped into. Offline that
        # map has its iterations and the fit is ~identity; a real-time map mapped for a few iterations renders
        # colours that read as a gain on every keyframe (0.86-0.91 on rendered Redwood), which is not the camera's.
        gain = fitted.exposure[:3]
        bias = self._map_colour_bias(self.keyframes[kf.id - 1])
        if bias is not None:
            gain = gain - bias[:3]
        if np.abs(gain).max() <= self.cfg.exposure.auto_threshold:
            return
        self.exposure_active, self.exposure_from = True, kf.id
        self.mapper.exposure = self.cfg.exposure
        for k in self.keyframes:
            k.exposure, k.exposure_prior = exposure.identity(), exposure.identity()
        self._fit_exposure(kf, first_of_submap=first_of_submap, fitted=fitted)

    def _map_colour_bias(self, kf: Keyframe) -> np.ndarray | None:
        """The exposure kf's image reads against the render of its own submap at its pose (slam.dense.mapping.
        exposure.fit; None when too few pixels agree): what the map's colours miss of a keyframe it was fitted to."""
        s = self.gmap.submaps[kf.submap_id]
        f = kf.map_rgbd if kf.map_rgbd is not None else kf.small  # packed ones decode as they are read
        if not len(s) or f is None:
            return None
        r = self._fit_to(s, kf.T_local_cam, f)
        return None if r is None else r.exposure

    def _fit_to(self, submap, T_local_cam: np.ndarray, f) -> "exposure.Fit | None":
        """The exposure frame `f` reads against `submap` rendered at T_local_cam (slam.dense.mapping.exposure.fit)."""
        with torch.no_grad():
            out = render(submap.params, viewmat_from_pose(T_local_cam), f.camera)
        return exposure.fit(out.color.clamp(0, 1).numpy(), out.alpha.numpy(), out.depth_normalised.numpy(),
                            f.color.astype(np.float32) / 255.0, f.depth, min_pixels=self.cfg.exposure.min_pixels)

    def _exposure_fit(self, kf: Keyframe, first_of_submap: bool) -> "exposure.Fit | None":
        """kf's exposure fitted to the render of the map already there: the active submap at its pose, or for a
        submap's first keyframe, the previous submap and every earlier one whose origin lies within
        exposure.revisit_radius (a revisit ties the new submap's colours to the ones that saw the place first, as
        a loop closes a chain of poses). None: too few pixels agree."""
        cfg = self.cfg.exposure
        s = self.gmap.submaps[kf.submap_id]
        f = kf.map_rgbd
        if first_of_submap:
            T_world = s.T_world_local @ kf.T_local_cam
            others = [m for m in self.gmap.submaps if m.id != s.id and len(m)]
            near = [m for m in others[:-1] if np.linalg.norm(m.T_world_local[:3, 3] - T_world[:3, 3])
                    < cfg.revisit_radius]
            refs = [(m, se3.inverse(m.T_world_local) @ T_world) for m in near + others[-1:]]
        else:
            refs = [(s, kf.T_local_cam)]
        fits = [self._fit_to(ref, T, f) for ref, T in refs if len(ref)]
        return exposure.combine([r for r in fits if r is not None])

    def _fit_exposure(self, kf: Keyframe, *, first_of_submap: bool, fitted: "exposure.Fit | None" = None) -> None:
        """Set kf's exposure (slam.dense.mapping.exposure) from the map already there (`_exposure_fit`, or
        `fitted` when the caller has it). The agent's first keyframe holds the gauge (identity); too little
        agreement keeps the previous keyframe's; an implausible step from it (a black frame, an auto-exposure
        reset) marks kf an outlier."""
        cfg = self.cfg.exposure
        if kf.id == 0:
            kf.exposure, kf.exposure_prior = exposure.identity(), exposure.identity()
            return
        prev = self.keyframes[kf.id - 1].exposure  # the keyframe before it
        prev = exposure.identity() if prev is None else prev
        f = kf.map_rgbd
        if fitted is None:
            fitted = self._exposure_fit(kf, first_of_submap)
        mean = float(f.color.mean()) / 255.0
        if fitted is None:
            kf.exposure_outlier = not 0.03 < mean < 0.97
            e = prev.copy()
        else:
            kf.exposure_outlier = exposure.is_outlier(fitted.exposure, prev, cfg.max_gain)
            e = prev.copy() if kf.exposure_outlier else fitted.exposure
        kf.exposure, kf.exposure_prior = e, e.copy()

    def _map(self, kf: Keyframe, *, iterations: int | None = None, stop=None) -> MappingStats:
        """Map keyframe `kf` into its submap: mapping.first_iterations for a submap's first keyframe, else
        mapping.iterations (or `iterations`); stop(i), if given, ends the optimisation after i iterations."""
        s = self.gmap.submaps[kf.submap_id]
        mks = self.map_keyframes(s)
        if iterations is None:
            iterations = self.cfg.mapping.first_iterations if len(mks) == 1 else self.cfg.mapping.iterations
        return self.mapper.map(self.gmap, s, mks, iterations, stop=stop)

    def map_keyframes(self, submap) -> list[MapKeyframe]:
        """The keyframes of `submap` as its mapping optimises them (their mapping-resolution images, exposures)."""
        # a submap's first keyframe holds its colour gauge; an outlier keeps the exposure it inherited
        kfs = [self.keyframes[i] for i in submap.keyframe_ids]
        return [MapKeyframe(k.T_local_cam, k.map_rgbd, k.exposure, k.exposure_prior,
                            exposure_fixed=i == 0 or k.exposure_outlier, exposure_outlier=k.exposure_outlier)
                for i, k in enumerate(kfs)]

    def _detect_loops(self, kf: Keyframe, information: np.ndarray | None = None) -> None:
        """Add `kf` to the loop closer and look for loops; `information`: the odometry edge's information since
        the previous keyframe (None: the tracking chain's, which is then restarted)."""
        if information is None:
            information = self._chain.information()
            self._chain.reset()
        self.loops.add_keyframe(kf, self.keyframes, self.gmap, information)
        if self.cfg.loop_closure.enabled and self.loops.detect(kf, self.keyframes, self.gmap):
            self.loops.optimise(self.keyframes, self.gmap)

    # ---- results ----------------------------------------------------------------------------------------------

    def trajectory(self, *, per_keyframe: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps [N], T_world_cam [N, 4, 4]) of every tracked frame, with the current submap frames (and
        following its keyframe's refined pose, once the map refinement refined it: slam.dense.submaps.frame_local_poses).

        per_keyframe=False: every frame moves rigidly with its submap (eq. 14), consistent with the map.
        per_keyframe=True: a frame follows the pose-graph optimum of the last keyframe before it in its submap
        (T = T_kf^opt · T_kf_local⁻¹ · T_frame_local; LoopCloser.optimum) — the trajectory the pose graph
        estimates, as a team's server scores it (Server.global_trajectory). Frames whose keyframe is not in the
        last applied optimum, or whose keyframe the map refinement refined, are placed as with False."""
        if not self.poses:
            return np.zeros(0), np.zeros((0, 4, 4))
        local = frame_local_poses(self.poses, self.keyframes)
        T = np.stack([self.gmap.submaps[p.submap_id].T_world_local @ L for p, L in zip(self.poses, local)])
        if per_keyframe and self.loops.optimum:
            follow_keyframe_optimum(T, self.poses, self.keyframes, lambda kf: self.loops.optimum.get(kf.id))
        return np.array([p.timestamp for p in self.poses]), T

    def trajectory_no_lc(self) -> tuple[np.ndarray, np.ndarray]:
        """The same frames as `trajectory`, placed as tracking alone places them (loop closures left out)."""
        if not self.poses:
            return np.zeros(0), np.zeros((0, 4, 4))
        T = np.stack([self.gmap.submaps[p.submap_id].T_world_local_no_lc @ p.T_local_cam for p in self.poses])
        return np.array([p.timestamp for p in self.poses]), T

    def keyframe_world_poses(self) -> np.ndarray:
        return np.stack([world_pose(self.gmap, k) for k in self.keyframes]) if self.keyframes else np.zeros((0, 4, 4))

    def display_map(self):
        """The merged map (world frame) with its colours as a typical keyframe saw them: what map.ply holds
        (slam.dense.mapping.exposure.for_display; the map's own colours when the exposure model is off)."""
        return exposure.for_display(self.gmap.merged(), self.keyframes)

    def render_keyframe(self, kf: Keyframe, camera: PinholeCamera) -> tuple[torch.Tensor, torch.Tensor]:
        """Render `kf`'s own submap at its pose: (color [H, W, 3], depth [H, W]) — the training-view render."""
        s = self.gmap.submaps[kf.submap_id]
        with torch.no_grad():
            out = render(s.params, viewmat_from_pose(kf.T_local), camera)
        return out.color.clamp(0, 1), out.depth_normalised
