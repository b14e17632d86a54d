"""The server's global map refinement (GRAND-SLAM: "the global map is refined"): for every component of the team,
its merged map is optimised over all its keyframes at their optimised poses (slam.map_refine), then every Gaussian
is handed back to its submap, in the submap's local frame so later moves still apply, and each submap is pruned as
mapping prunes."""

from __future__ import annotations

from kernels import se3

from .gaussian_map import GaussianMap, GaussianParams, transform_params
from .map_refine import RefineView, refine_map
from .render import viewmat_from_pose


def refine_components(server, cfg, mapping, *, reference: bool = False) -> dict:
    """Refine each component of `server` (slam.server.Server) in place. cfg: MapRefineConfig; mapping:
    MappingConfig (loss, learning rates, pruning). Returns per-component statistics keyed by the root agent."""
    out = {}
    for root, members in server.components().items():
        parts, views = [], []  # (submap, T component <- local, count)
        for a in members:
            s = server.slots[a]
            for sm in s.agent.gmap.submaps:
                if len(sm):
                    parts.append((sm, s.T_global_world @ sm.T_world_local, len(sm)))
            for kf in s.agent.keyframes:
                f = kf.map_rgbd if cfg.views == "mapping" and kf.map_rgbd is not None else kf.small
                views.append(RefineView(viewmat_from_pose(se3.project_rigid(server.global_pose(a, kf))),
                                        f.color_tensor(), f.depth_tensor(), f.camera))
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
        out[server.slots[root].agent.name] = {"iterations": st.iterations, "keyframes": st.views,
                                              "gaussians": st.gaussians, "hidden_dropped": hidden, "pruned": pruned,
                                              "loss_first": st.loss_first, "loss_last": st.loss_last,
                                              "seconds": st.seconds}
    return out
