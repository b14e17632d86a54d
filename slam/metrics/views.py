"""Rendering quality of a Gaussian map against input frames, at two resolutions: the pipeline's working
resolution (`image.max_width`, what tracking and, by default, mapping see) and the input resolution (the frame
as it was read, no downsampling). Shared by `swarmsplat run` (slam.run.sequence) and the team results
(slam.run.team_results) so both say the same thing under the same keys:

  psnr, ssim, depth_l1, psnr_valid_depth                      at `render_resolution` [w, h] (working)
  psnr_input_resolution, ssim_input_resolution, ...           at `input_resolution` [w, h]

When the two resolutions are equal the map is rendered once and the *_input_resolution figures are copies.
Each keyframe is rendered as its camera saw the map: with its exposure and white balance (slam.dense.mapping.exposure,
when the model is on; psnr_raw then scores the map's colours as they are); a held-out frame with the exposure
interpolated from the keyframes around it (`held_out_exposure`).
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
from swarmsplat.slam.dense.submaps import world_pose
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


def score_frame(params: GaussianParams, T_local_cam: np.ndarray, ref: RGBD, exposure: np.ndarray | None = None,
                display: np.ndarray | None = None) -> tuple[dict, torch.Tensor]:
    """Render `params` at T_local_cam [4, 4] (camera-to-local) with ref's camera, as a camera of `exposure` sees
    it (slam.dense.mapping.exposure; None: the map's colours as they are), and score it against `ref`.
    Returns ({psnr, ssim, depth_l1, psnr_valid_depth} (None where undefined), plus psnr_raw when an exposure is
    given: the map's colours as map.ply holds them, without the keyframe's own exposure (the map's colours times
    `display` [3], the keyframes' median gain, slam.dense.mapping.exposure.for_display; None: as they are);
    rendered colour [H, W, 3])."""
    from swarmsplat.slam.dense.mapping.exposure import apply
    from swarmsplat.slam.metrics import depth_l1, psnr, ssim

    with torch.no_grad():
        o = render(params, viewmat_from_pose(T_local_cam), ref.camera)
        color = apply(o.color, o.alpha, exposure).clamp(0, 1)
    pred, gt = color.permute(2, 0, 1), ref.color_tensor().permute(2, 0, 1)
    valid = ref.depth > 0
    s = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "depth_l1": None, "psnr_valid_depth": None}
    if exposure is not None:
        shown = o.color if display is None else o.color * torch.as_tensor(display, dtype=o.color.dtype)
        s["psnr_raw"] = psnr(shown.clamp(0, 1).permute(2, 0, 1), gt)
    if valid.any():
        s["depth_l1"] = depth_l1(o.depth_normalised, torch.as_tensor(ref.depth))
        s["psnr_valid_depth"] = psnr(pred, gt, mask=torch.as_tensor(valid))
    return s, color


def score_view(params: GaussianParams, T_local_cam: np.ndarray, color: np.ndarray, depth: np.ndarray,
               camera: PinholeCamera, cfg: SlamConfig, *, input_resolution: bool = True,
               exposure: np.ndarray | None = None, display: np.ndarray | None = None) -> tuple[dict, RGBD, torch.Tensor]:
    """One view at both resolutions. color [H, W, 3] uint8 and depth [H, W] metres are the input frame of
    `camera`; `exposure` and `display` as in score_frame. Returns (scores keyed as in the module docstring, working reference
    frame, working render)."""
    work, full = reference_frames(color, depth, camera, cfg)
    s, rendered = score_frame(params, T_local_cam, work, exposure, display)
    if input_resolution:
        same = work.camera.width == full.camera.width and work.camera.height == full.camera.height
        s_in = s if same else score_frame(params, T_local_cam, full, exposure, display)[0]
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


def keyframe_metrics(agent, seq, *, own: bool = True, merged: bool = True, held_out: int = 64) -> dict:
    """Training-view quality of one agent at the working and the input resolution. own: every keyframe rendered
    from its own submap at its pose (the keys in the module docstring). merged: every keyframe rendered from the
    merged map, every submap at its final place, at the keyframe's final pose (the same keys with MERGED before
    any resolution suffix, e.g. psnr_merged, psnr_merged_input_resolution: what a team reports as psnr). Plus
    render_views and both resolutions. With merged, also up to `held_out` tracked frames that are not keyframes
    (evenly spread; no mapping or refinement step saw them), from the merged map at their trajectory pose with the
    exposure of the keyframes around them: psnr_novel, ssim_novel (and _input_resolution), novel_views."""
    from swarmsplat.slam.dense.mapping.exposure import display_gain

    scores, merged_scores, novel_scores = [], [], []
    merged_map = agent.gmap.merged() if merged else None
    display = display_gain(agent.keyframes)
    for kf, T_world in zip(agent.keyframes, agent.keyframe_world_poses()):
        f = seq[kf.frame_index]
        if own:
            scores.append(score_view(agent.gmap.submaps[kf.submap_id].params, kf.T_local, f.color, f.depth,
                                     seq.camera, agent.cfg, exposure=kf.exposure, display=display)[0])
        if merged:
            merged_scores.append(score_view(merged_map, T_world, f.color, f.depth, seq.camera, agent.cfg,
                                            exposure=kf.exposure, display=display)[0])
    late = list(agent.late_views) if merged else []
    late_scores = [score_view(merged_map, T_world, seq[lv.frame_index].color, seq[lv.frame_index].depth, seq.camera,
                              agent.cfg, exposure=lv.exposure, display=display)[0]
                   for lv, T_world in zip(late, [world_pose(agent.gmap, lv) for lv in late])]
    if merged and held_out > 0 and agent.poses:
        kf_frames = {kf.frame_index for kf in agent.keyframes + late}  # the refinement fitted late views too
        _, T_all = agent.trajectory()
        held = [(rec.frame_index, T_all[i]) for i, rec in enumerate(agent.poses) if rec.frame_index not in kf_frames]
        if len(held) > held_out:
            held = [held[i] for i in np.unique(np.linspace(0, len(held) - 1, held_out).round().astype(int))]
        for index, T in held:
            f = seq[index]
            novel_scores.append(score_view(merged_map, T, f.color, f.depth, seq.camera, agent.cfg,
                                           exposure=held_out_exposure(agent.keyframes, index),
                                           display=display)[0])
    out = {"render_views": len(agent.keyframes), **resolutions(seq.camera, agent.cfg)}
    if own:
        means = mean_scores(scores)
        out.update({k: means.get(k) for k in METRICS} | {k + INPUT: means.get(k + INPUT) for k in METRICS})
        if means.get("psnr_raw") is not None:
            out["psnr_raw"] = means["psnr_raw"]
    if merged:
        mm = mean_scores(merged_scores)
        out.update({k + MERGED: mm.get(k) for k in METRICS} | {k + MERGED + INPUT: mm.get(k + INPUT) for k in METRICS})
        if mm.get("psnr_raw") is not None:
            out["psnr" + MERGED + "_raw"] = mm["psnr_raw"]
        nv = mean_scores(novel_scores)
        out.update(psnr_novel=nv.get("psnr"), ssim_novel=nv.get("ssim"), psnr_novel_input_resolution=nv.get("psnr" + INPUT),
                   ssim_novel_input_resolution=nv.get("ssim" + INPUT), novel_views=len(novel_scores))
        if late:  # the frames the refinement fitted beside the keyframes (a real-time run's late views)
            lm = mean_scores(late_scores)
            out.update(psnr_late_views=lm.get("psnr"), ssim_late_views=lm.get("ssim"), late_views=len(late))
    return out


def held_out_exposure(keyframes, frame_index: int) -> np.ndarray | None:
    """The exposure of a frame that is not a keyframe (slam.dense.mapping.exposure.interpolated): from the
    keyframes around it, never from the frame's own image, so a held-out score stays a prediction."""
    from swarmsplat.slam.dense.mapping.exposure import interpolated

    return interpolated(keyframes, frame_index)


def exposure_record(keyframes) -> dict:
    """metrics.json `exposure`: the keyframes' exposures (slam.dense.mapping.exposure.summary) and how the renders
    above were scored against them."""
    from swarmsplat.slam.dense.mapping.exposure import display_gain, summary

    rec = summary([k.exposure for k in keyframes], sum(1 for k in keyframes if k.exposure_outlier))
    if rec["keyframes"]:
        gain = display_gain(keyframes)
        if gain is not None:
            rec["display_gain"] = [float(g) for g in gain]
        rec["evaluation"] = ("keyframes rendered with their own exposure; held-out frames with the exposure "
                             "interpolated from the keyframes around them; psnr_raw / psnr_merged_raw: the map's "
                             "colours as map.ply holds them (times display_gain, the keyframes' median gain), "
                             "without each view's own exposure")
    return rec
