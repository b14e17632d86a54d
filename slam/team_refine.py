"""Global map refinement (GRAND-SLAM: "the global map is refined"): a merged map is optimised over all its
keyframes at their optimised poses (slam.map_refine), then every Gaussian is handed back to its submap, in the
submap's local frame so later moves still apply, and each submap is pruned as mapping prunes.

The server refines every component of a team (`refine_components`); a single agent's run refines its own merged
map the same way (`refine_agent`): its submaps overlap as a team's do (every new submap seeds its whole first view
again), and loop closure has moved them since mapping fitted them.
"""

from __future__ import annotations

from kernels import se3

from .gaussian_map import GaussianMap, GaussianParams, transform_params
from .map_refine import RefineView, refine_map
from .render import viewmat_from_pose


def _view(kf, T_frame_cam, cfg) -> RefineView:
    f = kf.map_rgbd if cfg.views == "mapping" and kf.map_rgbd is not None else kf.small
    return RefineView(viewmat_from_pose(se3.project_rigid(T_frame_cam)), f.color_tensor(), f.depth_tensor(),
                      f.camera)


def _refine_parts(parts, views, cfg, mapping, reference: bool) -> dict:
    """parts: [(submap, T frame <- submap local)]; refine their merged map over `views` (in that frame) and hand
    each submap its surviving Gaussians back. Returns the statistics."""
    parts = [(sm, T, len(sm)) for sm, T in parts if len(sm)]
    merged = GaussianParams.concat([transform_params(sm.params, T) for sm, T, _ in parts])
    refined, keep, st = refine_map(merged, views, cfg, mapping, reference=reference)
    hidden = int((~keep).sum())
    pruned, start, at = 0, 0, 0  # start: index in merged; at: index in refined (kept Gaussians only)
    for sm, T, n in parts:
        k = int(keep[start:start + n].sum())
        part = refined.select(slice(at, at + k))
        start, at = start + n, at + k
        sm.params = transform_params(part, se3.inverse(T))
        pruned += GaussianMap.prune(sm, min_opacity=mapping.prune_min_opacity, max_scale=mapping.prune_max_scale)
    return {"iterations": st.iterations, "keyframes": st.views, "gaussians": st.gaussians, "hidden_dropped": hidden,
            "pruned": pruned, "loss_first": st.loss_first, "loss_last": st.loss_last, "seconds": st.seconds}


def refine_components(server, cfg, mapping, *, reference: bool = False) -> dict:
    """Refine each component of `server` (slam.server.Server) in place. cfg: MapRefineConfig; mapping:
    MappingConfig (loss, learning rates, pruning). Returns per-component statistics keyed by the root agent."""
    out = {}
    for root, members in server.components().items():
        parts, views = [], []
        for a in members:
            s = server.slots[a]
            parts += [(sm, s.T_global_world @ sm.T_world_local) for sm in s.agent.gmap.submaps]
            views += [_view(kf, server.global_pose(a, kf), cfg) for kf in s.agent.keyframes]
        out[server.slots[root].agent.name] = _refine_parts(parts, views, cfg, mapping, reference)
    return out


def refine_agent(agent, cfg, mapping, *, reference: bool = False) -> dict | None:
    """Refine one agent's merged map (world frame) over its keyframes, in place; None when there is nothing to
    refine (refinement off, or no keyframe)."""
    if cfg.iterations_per_keyframe <= 0 or cfg.max_iterations <= 0 or not agent.keyframes:
        return None
    poses = agent.keyframe_world_poses()
    views = [_view(kf, T, cfg) for kf, T in zip(agent.keyframes, poses)]
    return _refine_parts([(sm, sm.T_world_local) for sm in agent.gmap.submaps], views, cfg, mapping, reference)
