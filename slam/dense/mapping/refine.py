"""Global map refinement (GRAND-SLAM: "the global map is refined"): a merged map is optimised over all its
keyframes at their optimised poses (slam.dense.mapping.refine_merged), then every Gaussian is handed back to its submap, in the
submap's local frame so later moves still apply, and each submap is pruned as mapping prunes.

The server refines every component of a team (`refine_components`); a single agent's run refines its own merged
map the same way (`refine_agent`): its submaps overlap as a team's do (every new submap seeds its whole first view
again), and loop closure has moved them since mapping fitted them. With `map_refine.refine_poses` each keyframe
gets its refined pose back too, in its submap's frame (Keyframe.T_local_refined).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from swarmsplat.kernels import se3

from swarmsplat.slam.dense.gaussian_map import GaussianMap, GaussianParams, transform_params
from swarmsplat.slam.dense.submaps import world_pose
from swarmsplat.slam.dense.mapping.refine_merged import RefineView, ViewCache, refines_poses
from .exposure import interpolated, median_gauge
from .refine_regions import refine_by_region
from swarmsplat.slam.dense.packed import PackedRGBD
from .mapper import fallback_depth
from .overlap_cull import OwnerView, owner_keep
from swarmsplat.slam.dense.render import viewmat_from_pose


def _view(kf, T_frame_cam, cfg, cache: ViewCache | None = None) -> RefineView:
    f = kf.map_rgbd if cfg.views == "mapping" and kf.map_rgbd is not None else kf.small
    # A stored keyframe's images stay as stored and are decoded when used, through `cache` (bounded memory over a
    # long mission); the active submap's raw ones are made tensors once.
    ex = {"exposure": kf.exposure, "exposure_prior": kf.exposure_prior, "exposure_outlier": kf.exposure_outlier}
    if isinstance(f, PackedRGBD):
        return RefineView(viewmat_from_pose(se3.project_rigid(T_frame_cam)), None, None, f.camera, frame=f,
                          cache=cache, **ex)
    return RefineView(viewmat_from_pose(se3.project_rigid(T_frame_cam)), f.color_tensor(), f.depth_tensor(),
                      f.camera, **ex)


def _overlap_keep(parts, views, view_submaps, cfg, mapping, means):
    """keep [N] of slam.dense.mapping.overlap_cull over `means` (the parts' Gaussians' centres in the frame, in
    order); view_submaps[i]: the submap
    of views[i]. With mapping.seed_without_depth, each view's large no-depth regions (where mapping seeded without
    depth, slam.dense.mapping.mapper.fallback_depth) decide the owner of the Gaussians there."""
    index = {id(sm): i for i, (sm, _, _) in enumerate(parts)}
    part = torch.cat([torch.full((n,), i, dtype=torch.long) for i, (_, _, n) in enumerate(parts)])

    def owner(v, sm):
        depth = v.read(cached=False)[1]
        no_depth = (torch.as_tensor(fallback_depth(depth.numpy(), mapping.no_depth_min_region) > 0)
                    if mapping.seed_without_depth else None)
        return OwnerView(index[id(sm)], v.viewmat, depth, v.camera, no_depth)

    # one view at a time (its depth decoded when the cull reaches it, once, past the refinement's cache), not
    # every view's images at once
    owners = (owner(v, sm) for v, sm in zip(views, view_submaps) if id(sm) in index)
    return owner_keep(means, part, owners, tol_abs=cfg.overlap_depth_tolerance,
                      tol_rel=cfg.overlap_depth_tolerance_rel)


def _frame_means(params: GaussianParams, T: np.ndarray) -> torch.Tensor:
    """[N, 3] the centres of `params` in the frame T [4, 4] (frame <- local): transform_params's means alone."""
    R = torch.as_tensor(np.asarray(T, dtype=np.float64)[:3, :3], dtype=params.means.dtype)
    t = torch.as_tensor(np.asarray(T, dtype=np.float64)[:3, 3], dtype=params.means.dtype)
    with torch.no_grad():
        return params.means @ R.T + t


def _refine_parts(parts, views, view_keyframes, cfg, mapping, fixed_views=None, exposure=None,
                  exposure_gauge=None) -> dict:
    """parts: [(submap, T frame <- submap local)]; refine their merged map over `views` (in that frame;
    view_keyframes[i] = (submap, keyframe) of views[i]), hand each submap its surviving Gaussians back and each
    keyframe its refined pose (with cfg.refine_poses). Returns the statistics."""
    t0 = time.perf_counter()
    view_submaps = [sm for sm, _ in view_keyframes]
    parts = [(sm, T, len(sm)) for sm, T in parts if len(sm)]
    total = sum(n for _, _, n in parts)
    runs = cfg.iterations_per_keyframe > 0 and cfg.max_iterations > 0 and views and total
    owned = torch.ones(total, dtype=torch.bool)
    if runs and cfg.overlap_cull:  # on the centres alone: a revisited place merges several copies of each surface
        owned = _overlap_keep(parts, views, view_submaps, cfg, mapping,
                              torch.cat([_frame_means(sm.params, T) for sm, T, _ in parts]))
    cull_s = time.perf_counter() - t0
    # The merged map holds the owned Gaussians only, each part selected before they are put together.
    starts = np.cumsum([0] + [n for _, _, n in parts])
    merged = GaussianParams.concat([transform_params(sm.params, T).select(owned[a:a + n])
                                    for (sm, T, n), a in zip(parts, starts)])
    refined, kept, st, regions = refine_by_region(merged, views, cfg, mapping, fixed_views=fixed_views,
                                                  exposure=exposure, exposure_gauge=exposure_gauge)
    gauge = None
    if st.exposures is not None:  # each keyframe keeps its refined exposure (slam.dense.mapping.exposure)
        for (_, kf), e in zip(view_keyframes, st.exposures):
            if e is not None and kf.exposure is not None:
                kf.exposure = np.asarray(e, dtype=np.float64)
        if exposure is not None and exposure.map_gauge == "median":  # the map's own colours as a typical keyframe sees them
            gauge = median_gauge(refined.colors, [kf for _, kf in view_keyframes])
    keep = owned.clone()
    keep[owned] = kept
    overlap, hidden = int((~owned).sum()), int((~kept).sum())
    pruned, start, at = 0, 0, 0  # start: index in merged; at: index in refined (kept Gaussians only)
    for sm, T, n in parts:
        k = int(keep[start:start + n].sum())
        part = refined.select(slice(at, at + k))
        start, at = start + n, at + k
        sm.params = transform_params(part, se3.inverse(T))
        pruned += GaussianMap.prune(sm, min_opacity=mapping.prune_min_opacity, max_scale=mapping.prune_max_scale)
    poses = {}
    if st.viewmats is not None:
        frame_of = {id(sm): T for sm, T, _ in parts}
        for (sm, kf), vm in zip(view_keyframes, st.viewmats):
            if id(sm) in frame_of:  # T_local = (frame <- local)^-1 (frame <- camera)
                kf.T_local_refined = se3.project_rigid(
                    se3.inverse(frame_of[id(sm)]) @ se3.inverse(vm.double().numpy()))
        rot, trans = st.pose_moves[:, 0], st.pose_moves[:, 1]
        poses = {"pose_rotation_deg_median": float(np.degrees(np.median(rot))),
                 "pose_rotation_deg_max": float(np.degrees(rot.max())),
                 "pose_translation_m_median": float(np.median(trans)), "pose_translation_m_max": float(trans.max())}
    return {"iterations": st.iterations, "keyframes": st.views, "gaussians": total, "overlap_dropped": overlap,
            "hidden_dropped": hidden,
            "pruned": pruned, "loss_first": st.loss_first, "loss_last": st.loss_last,
            "overlap_cull_seconds": cull_s, **regions, **poses, "seconds": time.perf_counter() - t0,
            **({} if gauge is None else {"exposure_gauge_gain": [float(g) for g in np.exp(gauge)]})}


def _start_pose(server, a, kf, moved: bool):
    """Where a keyframe's view starts: with pose refinement, from its pose-graph optimum (the best estimate the
    trajectory reports; measured on the demo at 320 px it keeps the team ATE closer to the unrefined one than
    starting from the submap-rigid pose); otherwise at the submap-rigid pose the map was placed with. moved:
    whether the refinement refines the poses (refines_poses)."""
    if moved and server.last_graph is not None and kf.T_local_refined is None:
        T = server.last_graph[1].get(server.key(a, kf.id))
        if T is not None:
            return T
    return server.global_pose(a, kf)


def refine_components(server, cfg, mapping, exposure=None) -> dict:
    """Refine each component of `server` (slam.dense.team.server.Server) in place. cfg: MapRefineConfig; mapping:
    MappingConfig (loss, learning rates, pruning); exposure: ExposureConfig to refine the keyframes' exposures
    with the map (None: they stay as they are). Returns per-component statistics keyed by the root agent."""
    out = {}
    for root, members in server.components().items():
        parts, views, view_keyframes, fixed = [], [], [], set()
        cache = ViewCache(cfg.view_cache_mb * 1e6)
        moved = refines_poses(cfg, [kf for a in members for kf in server.slots[a].agent.keyframes])
        for a in members:
            s = server.slots[a]
            if s.agent.keyframes:  # each agent's first keyframe holds its gauge (its place in the team's frame)
                fixed.add(len(views))
            parts += [(sm, s.T_global_world @ sm.T_world_local) for sm in s.agent.gmap.submaps]
            views += [_view(kf, _start_pose(server, a, kf, moved), cfg, cache) for kf in s.agent.keyframes]
            view_keyframes += [(s.agent.gmap.submaps[kf.submap_id], kf) for kf in s.agent.keyframes]
        out[server.slots[root].agent.name] = _refine_parts(parts, views, view_keyframes, cfg, mapping,
                                                           fixed or None, exposure,
                                                           {min(fixed)} if fixed else None)
    return out


def refine_agent(agent, cfg, mapping, exposure=None) -> dict | None:
    """Refine one agent's merged map (world frame) over its keyframes, in place (with their exposures, given an
    ExposureConfig `exposure`); None when there is nothing to refine (refinement off, or no keyframe)."""
    if cfg.iterations_per_keyframe <= 0 or cfg.max_iterations <= 0 or not agent.keyframes:
        return None
    late = list(agent.late_views)
    if late and exposure is not None:  # as a held-out frame's, from the keyframes around it; refined from there
        for lv in late:
            lv.exposure = interpolated(agent.keyframes, lv.frame_index)
            lv.exposure_prior = None if lv.exposure is None else lv.exposure.copy()
    kfs = agent.keyframes + late
    cache = ViewCache(cfg.view_cache_mb * 1e6)
    views = [_view(kf, world_pose(agent.gmap, kf), cfg, cache) for kf in kfs]
    view_keyframes = [(agent.gmap.submaps[kf.submap_id], kf) for kf in kfs]
    return _refine_parts([(sm, sm.T_world_local) for sm in agent.gmap.submaps], views, view_keyframes, cfg, mapping,
                         exposure=exposure)
