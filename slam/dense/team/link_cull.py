"""What of a finished submap an agent need not send its team server: the Gaussians the server's overlap cull
(slam.dense.mapping.overlap_cull, before the merged map is refined) drops anyway.

The cull gives each Gaussian to the submap of the keyframe that observes its centre on its depth surface from
closest, and drops it from every other submap. A Gaussian of submap S that one of the agent's own keyframes of
another submap observes from closer than all of S's keyframes is therefore dropped by the server whatever other
keyframes it holds: more keyframes can only name a closer owner, never S (all of S's keyframes are already
counted). When S is finished the agent holds S's keyframes, every earlier one and the first of the next submap,
which seeds its whole first view again; on the demo those alone name another owner for about half of what a
team agent's submaps hold (the server drops about four in five once it has every agent's keyframes).

The agent decides with the poses it has when it sends (its submaps placed by the server's latest correction);
the server decides with the final ones, so a Gaussian on the edge of the depth tolerance can go either way.

    keep = sent_gaussians(agent, submap_id)   # [N] bool over the submap's Gaussians, or None: send them all
"""

from __future__ import annotations

import numpy as np
import torch

from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.mapping.mapper import fallback_depth
from swarmsplat.slam.dense.mapping.overlap_cull import OwnerView, owner_keep
from swarmsplat.slam.dense.render import viewmat_from_pose


def server_culls(cfg: SlamConfig) -> bool:
    """True when the server's refinement runs its overlap cull (MapRefineConfig)."""
    rc = cfg.map_refine
    return rc.overlap_cull and rc.iterations_per_keyframe > 0 and rc.max_iterations > 0


def sent_gaussians(agent, submap_id: int) -> np.ndarray | None:
    """[N] bool over the Gaussians of `agent`'s (slam.dense.agent.Agent) finished submap `submap_id`: False for
    those the server's overlap cull drops whatever else it holds (module docstring); None when the server runs no
    such cull (send them all)."""
    cfg = agent.cfg
    if not server_culls(cfg):
        return None
    sms = agent.gmap.submaps
    sm = sms[submap_id]
    if len(sm) == 0:
        return None
    params = sm.params
    T = np.asarray(sm.T_world_local, dtype=np.float64)
    with torch.no_grad():
        means = params.means.double() @ torch.as_tensor(T[:3, :3]).T + torch.as_tensor(T[:3, 3])
    rc, mapping = cfg.map_refine, cfg.mapping

    def views():  # one at a time: a stored keyframe's depth is decoded when the cull reaches it
        for kf in agent.keyframes:
            f = kf.map_rgbd if rc.views == "mapping" and kf.map_rgbd is not None else kf.small
            T_world_cam = np.asarray(sms[kf.submap_id].T_world_local, dtype=np.float64) @ kf.T_local
            depth = np.asarray(f.depth, dtype=np.float32)
            no_depth = (torch.as_tensor(fallback_depth(depth, mapping.no_depth_min_region) > 0)
                        if mapping.seed_without_depth else None)
            yield OwnerView(int(kf.submap_id), viewmat_from_pose(se3.project_rigid(T_world_cam)),
                            torch.as_tensor(depth), f.camera, no_depth)

    part = torch.full((len(means),), int(submap_id), dtype=torch.long)
    keep = owner_keep(means.float(), part, views(), tol_abs=rc.overlap_depth_tolerance,
                      tol_rel=rc.overlap_depth_tolerance_rel)
    return keep.numpy()
