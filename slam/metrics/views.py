"""Rendering quality of a Gaussian map against input frames, at two resolutions: the pipeline's working
resolution (`image.max_width`, what tracking and, by default, mapping see) and the input resolution (the frame
as it was read, no downsampling). Shared by `swarmsplat run` (slam.run.sequence) and the team results
(slam.run.team_results) so both say the same thing under the same keys:

  psnr, ssim, depth_l1, psnr_valid_depth                      at `render_resolution` [w, h] (working)
  psnr_input_resolution, ssim_input_resolution, ...           at `input_resolution` [w, h]

When the two resolutions are equal the map is rendered once and the *_input_resolution figures are copies.
A single agent's run reports its keyframes rendered from their own submaps (psnr, ...: the mapping stage's result,
scored before the final map refinement) and from its final merged map (psnr_merged, ...: overlapping submaps blend
there, as in a team's merged map).
Colour is clamped to [0, 1]; depth L1 compares the rendered expected surface depth (depth / alpha) with the
valid input depth (metres); psnr_valid_depth leaves out pixels without valid depth (they get no Gaussians).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from swarmsplat.kernels.camera import PinholeCamera

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import RGBD, make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.render import render, viewmat_from_pose

METRICS = ("psnr", "ssim", "depth_l1", "psnr_valid_depth")
INPUT = "_input_resolution"


def reference_frames(color: np.ndarray, depth: np.ndarray, camera: PinholeCamera, cfg: SlamConfig) -> tuple[RGBD, RGBD]:
    """(working-resolution frame, input-resolution frame) of one input frame, cleaned as the pipeline does."""
    full = make_rgbd(color, depth, camera, min_depth=cfg.image.min_depth, max_depth=cfg.image.max_depth)
    return full.resized(cfg.image.max_width), full


def resolutions(camera: PinholeCamera, cfg: SlamConfig) -> dict:
    """{"render_resolution": [w, h] working, "input_resolution": [w, h]} for frames of `camera`."""
    w, h = int(camera.width), int(camera.height)
    mw = cfg.image.max_width
    if mw > 0 and w > mw:
        return {"render_resolution": [int(mw), max(1, int(round(h * mw / w)))], "input_resolution": [w, h]}
    return {"render_resolution": [w, h], "input_resolution": [w, h]}


def score_frame(params: GaussianParams, T_local_cam: np.ndarray, ref: RGBD) -> tuple[dict, torch.Tensor]:
    """Render `params` at T_local_cam [4, 4] (camera-to-local) with ref's camera and score it against `ref`.
    Returns ({psnr, ssim, depth_l1, psnr_valid_depth} (None where undefined), rendered colour [H, W, 3])."""
    from swarmsplat.slam.metrics import depth_l1, psnr, ssim

    with torch.no_grad():
        o = render(params, viewmat_from_pose(T_local_cam), ref.camera)
    color = o.color.clamp(0, 1)
    pred, gt = color.permute(2, 0, 1), ref.color_tensor().permute(2, 0, 1)
    valid = ref.depth > 0
    s = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "depth_l1": None, "psnr_valid_depth": None}
    if valid.any():
        s["depth_l1"] = depth_l1(o.depth_normalised, torch.as_tensor(ref.depth))
        s["psnr_valid_depth"] = psnr(pred, gt, mask=torch.as_tensor(valid))
    return s, color


def score_view(params: GaussianParams, T_local_cam: np.ndarray, color: np.ndarray, depth: np.ndarray,
               camera: PinholeCamera, cfg: SlamConfig, *, input_resolution: bool = True) -> tuple[dict, RGBD, torch.Tensor]:
    """One view at both resolutions. color [H, W, 3] uint8 and depth [H, W] metres are the input frame of
    `camera`. Returns (scores keyed as in the module docstring, working reference frame, working render)."""
    work, full = reference_frames(color, depth, camera, cfg)
    s, rendered = score_frame(params, T_local_cam, work)
    if input_resolution:
        same = work.camera.width == full.camera.width and work.camera.height == full.camera.height
        s_in = s if same else score_frame(params, T_local_cam, full)[0]
        s.update({k + INPUT: s_in[k] for k in METRICS})
    return s, work, rendered


def mean_scores(scores: list[dict]) -> dict:
    """Per-key mean over views, ignoring None / non-finite entries (None when nothing is left)."""
    keys = [k for s in scores for k in s]
    out = {}
    for k in dict.fromkeys(keys):
        v = [s[k] for s in scores if s.get(k) is not None and math.isfinite(s[k])]
        out[k] = float(np.mean(v)) if v else None
    return out


MERGED = "_merged"


def keyframe_metrics(agent, seq, *, own: bool = True, merged: bool = True) -> dict:
    """Training-view quality of one agent at the working and the input resolution. own: every keyframe rendered
    from its own submap at its pose (the keys in the module docstring). merged: every keyframe rendered from the
    merged map, every submap at its final place, at the keyframe's final pose (the same keys with MERGED before
    any resolution suffix, e.g. psnr_merged, psnr_merged_input_resolution: what a team reports as psnr). Plus
    render_views and both resolutions."""
    scores, merged_scores = [], []
    merged_map = agent.gmap.merged() if merged else None
    for kf, T_world in zip(agent.keyframes, agent.keyframe_world_poses()):
        f = seq[kf.frame_index]
        if own:
            scores.append(score_view(agent.gmap.submaps[kf.submap_id].params, kf.T_local, f.color, f.depth,
                                     seq.camera, agent.cfg)[0])
        if merged:
            merged_scores.append(score_view(merged_map, T_world, f.color, f.depth, seq.camera, agent.cfg)[0])
    out = {"render_views": len(agent.keyframes), **resolutions(seq.camera, agent.cfg)}
    if own:
        means = mean_scores(scores)
        out.update({k: means.get(k) for k in METRICS} | {k + INPUT: means.get(k + INPUT) for k in METRICS})
    if merged:
        mm = mean_scores(merged_scores)
        out.update({k + MERGED: mm.get(k) for k in METRICS} | {k + MERGED + INPUT: mm.get(k + INPUT) for k in METRICS})
    return out
