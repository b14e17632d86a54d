"""Loop verification by rendering: the matched agent's Gaussian submaps are rendered from the query keyframe's
hypothesised pose and compared with what the query camera actually saw. A Gaussian map can say what a point-cloud
check cannot: where the map has a surface *in front of* the observed one, the camera would have seen it, so the
hypothesis contradicts free space (a repeated structure matched in the wrong room, a wall matched to its mirror
image) even when the two clouds overlap well.

Scores over the query's valid depth pixels that the render covers (alpha > 0.5, "co-visible"):
    agree     |d_render - d_query| <= depth_abs + depth_rel * d_query
    violate   d_render < d_query - (free_abs + free_rel * d_query): the map occludes what the camera saw
    photometric error: mean |colour| over agreeing pixels after a per-channel gain and offset fitted there (real
    cameras change exposure and white balance between agents), in [0, 1] units.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from swarmsplat.kernels import se3

from swarmsplat.slam.dense.gaussian_map import GaussianParams, transform_params
from swarmsplat.slam.dense.render import render, viewmat_from_pose


@dataclass
class RenderScore:
    covisible: float  # fraction of the query's valid depth pixels the render covers
    agree: float  # fraction of co-visible pixels whose depths agree
    violate: float  # fraction of co-visible pixels where the map lies in front of the observed surface
    photometric: float  # mean absolute colour error on agreeing pixels after the gain/offset fit ([0, 1])
    pixels: int  # the query's valid depth pixels

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class RenderGate:
    """What a rendered view must show for a loop to count (server.render_check_*)."""

    min_covisible: float = 0.15
    min_agree: float = 0.5
    max_violate: float = 0.15
    max_photometric: float = 0.12

    def verdict(self, s: RenderScore) -> str:
        """'' when the score passes, else the reason."""
        if s.pixels == 0 or s.covisible < self.min_covisible:
            return f"rendered view covers {100 * s.covisible:.0f} % of the query's depth (< {100 * self.min_covisible:.0f} %)"
        if s.agree < self.min_agree:
            return f"rendered depth agrees on {100 * s.agree:.0f} % of co-visible pixels (< {100 * self.min_agree:.0f} %)"
        if s.violate > self.max_violate:
            return f"map in front of the observed surface on {100 * s.violate:.0f} % of co-visible pixels " \
                   f"(> {100 * self.max_violate:.0f} %)"
        if s.photometric > self.max_photometric:
            return f"photometric error {s.photometric:.3f} > {self.max_photometric}"
        return ""


def gaussians_in_world(gmap, submap_ids) -> GaussianParams:
    """The Gaussians of the given submaps of `gmap`, in the agent's world frame (each submap's T_world_local)."""
    parts = [transform_params(gmap.submaps[s].params, gmap.submaps[s].T_world_local) for s in sorted(set(submap_ids))
             if len(gmap.submaps[s])]
    return GaussianParams.concat(parts) if parts else GaussianParams.empty()


def score_view(params: GaussianParams, T_world_cam: np.ndarray, view, *, depth_abs: float = 0.05,
               depth_rel: float = 0.03, free_abs: float = 0.10, free_rel: float = 0.05) -> RenderScore:
    """Render `params` (world frame) from camera pose `T_world_cam` [4, 4] on `view`'s camera and score it
    against `view` (RGBD or PackedRGBD: colour uint8 [H, W, 3], depth metres [H, W], 0 invalid)."""
    dq = np.asarray(view.depth, dtype=np.float64)
    valid = dq > 0
    n = int(valid.sum())
    if n == 0 or len(params) == 0:
        return RenderScore(0.0, 0.0, 0.0, float("inf"), n)
    with torch.no_grad():
        out = render(params, viewmat_from_pose(se3.project_rigid(T_world_cam), dtype=params.means.dtype), view.camera)
    alpha = out.alpha.numpy().astype(np.float64)
    dr = out.depth_normalised.numpy().astype(np.float64)
    cov = valid & (alpha > 0.5) & (dr > 0)
    nc = int(cov.sum())
    if nc == 0:
        return RenderScore(0.0, 0.0, 0.0, float("inf"), n)
    d, r = dq[cov], dr[cov]
    agree = np.abs(r - d) <= depth_abs + depth_rel * d
    violate = r < d - (free_abs + free_rel * d)
    photometric = float("inf")
    if agree.sum() >= 10:
        c_r = (out.color.numpy().astype(np.float64) / np.maximum(alpha, 1e-3)[..., None])[cov][agree]
        c_q = (np.asarray(view.color, dtype=np.float64) / 255.0)[cov][agree]
        err = []
        for ch in range(3):  # least-squares gain and offset per channel: exposure and white balance
            A = np.stack([c_r[:, ch], np.ones(len(c_r))], 1)
            coef, *_ = np.linalg.lstsq(A, c_q[:, ch], rcond=None)
            err.append(np.abs(A @ coef - c_q[:, ch]))
        photometric = float(np.mean(err))
    return RenderScore(nc / n, float(agree.mean()), float(violate.mean()), photometric, n)


def score_loop(gmap, keyframes, match, T_match_query: np.ndarray, query_view, radius: int, *,
               exclude_submaps=()) -> RenderScore:
    """Render the submaps of the keyframes within `radius` ids of `match` (slam.dense.loops.local_clouds.
    window_keyframes) from the query camera's hypothesised pose, match's world pose @ T_match_query, and score it
    against `query_view` (the query keyframe's loop-closure copy). `exclude_submaps`: submap ids left out (within
    one agent, those the query's own window was mapped into, so the render is evidence independent of it)."""
    from swarmsplat.slam.dense.submaps import world_pose

    from .local_clouds import window_keyframes

    window = window_keyframes(keyframes, match, max(radius, 1))
    params = gaussians_in_world(gmap, [k.submap_id for k in window if k.submap_id not in set(exclude_submaps)])
    return score_view(params, world_pose(gmap, match) @ T_match_query, query_view)


def record_scores(target, s: RenderScore) -> None:
    """Copy a score onto a loop record or candidate (its render_* fields)."""
    target.render_covisible, target.render_agree = s.covisible, s.agree
    target.render_violate, target.render_photometric = s.violate, s.photometric
