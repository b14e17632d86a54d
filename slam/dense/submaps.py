"""Submap life cycle (GRAND-SLAM §III-B.1): when to start a new submap, and retiring the old one so memory stays
bounded by the active submap plus the stored (frozen) Gaussians and small keyframe copies."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels import se3

from swarmsplat.slam.config import SubmapConfig
from .frames import RGBD
from .gaussian_map import GaussianMap, Submap
from .packed import PackedRGBD, pack


@dataclass
class Keyframe:
    """A keyframe of the agent. Its world pose is `T_world_local` of its submap composed with its local pose, so
    moving the submap (pose-graph optimisation, eq. 14) moves the keyframe with it. The local pose is the tracked
    `T_local_cam`, or `T_local_refined` once the global map refinement has refined it (slam.dense.mapping.refine_merged): the map
    is fitted to that pose, and the frames tracked after the keyframe follow it (`frame_local_poses`)."""

    id: int
    frame_index: int
    timestamp: float
    submap_id: int
    T_local_cam: np.ndarray  # [4, 4]
    map_rgbd: RGBD | PackedRGBD | None  # mapping resolution; dropped when the submap is retired (unless kept)
    small: RGBD | PackedRGBD  # kept for loop-closure registration (SubmapConfig.keep_keyframe_width)
    descriptor: np.ndarray | None = None  # [D] unit vector
    T_local_refined: np.ndarray | None = None  # [4, 4] after the map refinement's pose refinement
    # The keyframe's exposure and white balance (slam.dense.mapping.exposure: [6] log gains, offsets; None when the
    # model is off), the value fitted when the keyframe was made (the regulariser's anchor), and whether its image
    # was an outlier (its colour left out of the loss).
    exposure: np.ndarray | None = None
    exposure_prior: np.ndarray | None = None
    exposure_outlier: bool = False

    @property
    def T_local(self) -> np.ndarray:
        """The keyframe's best pose in its submap: refined if it was, else as tracked."""
        return self.T_local_cam if self.T_local_refined is None else self.T_local_refined


def needs_new_submap(cfg: SubmapConfig, T_local_cam: np.ndarray, n_keyframes: int) -> bool:
    """True when the keyframe is further than d_max or θ_max from the active submap's first keyframe (the local
    origin), or the submap already holds `max_keyframes`."""
    moved = float(np.linalg.norm(T_local_cam[:3, 3]))
    turned = float(np.degrees(se3.rotation_angle(T_local_cam[:3, :3])))
    return moved > cfg.d_max or turned > cfg.theta_max_deg or n_keyframes >= cfg.max_keyframes


def start_submap(gmap: GaussianMap, T_world_cam: np.ndarray, keyframes: list[Keyframe], *,
                 keep_images: bool = False, compress: bool = False, prune_min_contribution: float = 0.0,
                 frame_store=None) -> Submap:
    """Retire the active submap (frozen Gaussians, keyframe images dropped except the small copies, unless
    `keep_images`: a team's server refines the merged map on them) and start a new one whose local frame is the
    camera at T_world_cam. With `compress` the retired keyframes' images that stay are packed losslessly
    (slam.dense.packed), decoded on each later read, and with a `frame_store` (slam.io.submap_files.KeyframeFiles)
    moved there out of memory. With `prune_min_contribution` > 0 the retired submap first
    loses the Gaussians that contribute less than that many pixels to each of its keyframes' renders. The
    retired Gaussians then go to the map's store, if it has one (GaussianMap.retire)."""
    if not gmap.submaps:
        return gmap.new_submap(T_world_cam)
    old = gmap.active
    own = [kf for kf in keyframes if kf.submap_id == old.id]
    if prune_min_contribution > 0 and len(old):
        prune_unseen(old, own, prune_min_contribution)
    retire_keyframes(own, keep_images=keep_images, compress=compress, frame_store=frame_store)
    new = gmap.new_submap(T_world_cam)
    gmap.retire(old)
    return new


def retire_keyframes(keyframes: list[Keyframe], *, keep_images: bool, compress: bool, frame_store=None) -> None:
    """What a finished submap's keyframes keep (see start_submap): the mapping-resolution images only with
    `keep_images`; packed with `compress`; packed ones moved to `frame_store` when given."""
    for kf in keyframes:
        kf.map_rgbd = (pack(kf.map_rgbd) if compress else kf.map_rgbd) if keep_images else None
        kf.small = pack(kf.small) if compress else kf.small
        if frame_store is not None:
            if isinstance(kf.small, PackedRGBD):
                kf.small.store(frame_store.small, kf.id)
            if isinstance(kf.map_rgbd, PackedRGBD):
                kf.map_rgbd.store(frame_store.mapping, kf.id)


def prune_unseen(submap: Submap, keyframes: list[Keyframe], min_contribution: float) -> int:
    """Drop the Gaussians of `submap` whose total blending weight (pixels; slam.dense.mapping.refine_merged.
    contributions) is below `min_contribution` in every one of `keyframes` (its own, at the mapping resolution,
    in its local frame). Returns how many were dropped."""
    from .mapping.refine_merged import RefineView, contributions
    from .render import viewmat_from_pose

    views = [RefineView(viewmat_from_pose(kf.T_local_cam), None, None, kf.map_rgbd.camera)
             for kf in keyframes if kf.map_rgbd is not None]
    if not views:
        return 0
    keep = contributions(submap.params, views) >= min_contribution
    dropped = int((~keep).sum())
    if dropped:
        submap.params = submap.params.select(keep)
    return dropped


def world_pose(gmap: GaussianMap, kf: Keyframe) -> np.ndarray:
    return gmap.submaps[kf.submap_id].T_world_local @ kf.T_local


def last_keyframes(poses, keyframes: list[Keyframe]) -> list[Keyframe | None]:
    """For each tracked frame (`poses`: records with frame_index, in tracking order) the last keyframe at or
    before it, if that keyframe is in the frame's submap (else None)."""
    kfs = sorted(keyframes, key=lambda k: k.frame_index)
    out, j, last = [], 0, None
    for rec in poses:
        while j < len(kfs) and kfs[j].frame_index <= rec.frame_index:
            last, j = kfs[j], j + 1
        out.append(last if last is not None and last.submap_id == rec.submap_id else None)
    return out


def follow_keyframe_optimum(T: np.ndarray, poses, keyframes: list[Keyframe], optimum_of) -> np.ndarray:
    """Move each frame of `T` [N, 4, 4] (the rigid placement of `poses`) to the pose-graph optimum of the last keyframe
    before it in its submap: T = T_kf^opt · T_kf_local⁻¹ · T_frame_local, T_kf^opt = optimum_of(kf) in T's frame
    (None: that keyframe has no optimum, the frame keeps its rigid pose). Frames of a keyframe the map refinement
    refined keep theirs too: the frames already follow its refined pose. In place; returns T."""
    for n, (rec, last) in enumerate(zip(poses, last_keyframes(poses, keyframes))):
        if last is None or last.T_local_refined is not None:
            continue
        T_kf = optimum_of(last)
        if T_kf is not None:
            T[n] = T_kf @ se3.inverse(last.T_local_cam) @ rec.T_local_cam
    return T


def frame_local_poses(poses, keyframes: list[Keyframe]) -> list[np.ndarray]:
    """Each tracked frame's pose in its submap (`poses`: records with frame_index, submap_id, T_local_cam, in
    tracking order): as tracked, except after a keyframe of the same submap whose pose was refined, where the frame
    keeps its tracked pose relative to that keyframe (T_refined · T_kf⁻¹ · T_frame)."""
    return [rec.T_local_cam if kf is None or kf.T_local_refined is None
            else kf.T_local_refined @ se3.inverse(kf.T_local_cam) @ rec.T_local_cam
            for rec, kf in zip(poses, last_keyframes(poses, keyframes))]
