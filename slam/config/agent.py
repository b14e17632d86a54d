"""Typed configuration of one GRAND-SLAM agent: nested pydantic models, YAML overrides, validated on load,
written next to the results (`to_yaml`). No global config: every component receives its own section.

Defaults work on the generated 320x240 sequences and on TUM-like real data at 640x480 (which the agent works on
at `image.max_width`, 320 by default, to suit a CPU).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ImageConfig(_Section):
    max_width: int = Field(320, ge=16, description="frames wider than this (pixels) are downsampled (area) for "
                                                   "the whole pipeline")
    min_depth: float = Field(0.1, gt=0, description="depth below this (metres) is treated as invalid")
    max_depth: float = Field(10.0, gt=0, description="depth beyond this (metres) is treated as invalid")
    min_valid_fraction: float = Field(0.05, ge=0, le=1, description="frames with fewer valid depth pixels are "
                                                                    "skipped with a warning")


class TrackingConfig(_Section):
    coarse: Literal["rgbd_odometry", "none"] = Field("rgbd_odometry", description="coarse frame-to-frame stage: "
                                                     "hybrid colour-depth odometry, or none (constant velocity)")
    coarse_max_width: int = Field(320, ge=16, description="resolution of the coarse frame-to-frame odometry")
    coarse_eval_max_width: int = Field(160, ge=16, description="width (pixels) at which the coarse odometry's "
                                       "result is scored (fitness, RMSE, information matrix): every s-th pixel of "
                                       "coarse_max_width, s = coarse_max_width // this")
    coarse_max_motion: float = Field(0.3, gt=0, description="a coarse step moving more than this (m) is "
                                                            "distrusted: constant velocity is used instead")
    recovery: bool = Field(True, description="when the coarse stage fails, retry it from a learned start (XFeat "
                           "matches + depth + RANSAC) against the previous frame, then re-localise against the "
                           "current submap's keyframes, before falling back to constant velocity "
                           "(slam.dense.tracking.recovery)")
    recovery_max_motion: float = Field(0.5, gt=0, description="recovery: a recovered step longer than this (m) is "
                                       "rejected")
    recovery_max_disagreement: float = Field(0.1, gt=0, description="recovery: reject when the odometry moves the "
                                             "learned start by more than this (m)")
    recovery_max_keyframes: int = Field(3, ge=0, description="recovery: newest keyframes of the current submap "
                                        "tried for re-localisation (0 = retry against the previous frame only)")
    recovery_top_k: int = Field(512, ge=16, description="recovery: XFeat keypoints per image")
    refine: bool = Field(True, description="frame-to-model refinement after the coarse stage (§III-C): "
                                          "Gauss-Newton against the active submap rendered at the last keyframe, "
                                          "with debias_view")
    refine_on_coarse_failure: bool = Field(True, description="run the refinement anyway when the coarse stage "
                                                            "fails (then it starts from constant velocity)")
    method: Literal["gauss_newton", "adam"] = Field(
        "gauss_newton", description="refinement: Gauss-Newton on hybrid point-to-plane + intensity residuals "
                                    "against the submap rendered once per map update, or Adam on eq. 5 through "
                                    "the rasteriser's pose gradient every iteration (slam.dense.tracking.tracker)")
    refine_max_width: int = Field(320, ge=16, description="width (pixels) of the frame-to-model refinement; the "
                                                          "model view is rendered at this width")
    pyramid_levels: int = Field(1, ge=1, le=4, description="refinement pyramid (each level halves the width)")
    iterations: int = Field(3, ge=0, description="Gauss-Newton steps per pyramid level (0 = no refinement)")
    step_tolerance: float = Field(1e-4, gt=0, description="Gauss-Newton: stop a level when a step moves less "
                                  "than this (m and rad)")
    photometric_weight: float = Field(0.3, ge=0, description="Gauss-Newton: intensity term weight (intensity in "
                                                             "[0, 1] against metres)")
    max_distance: float = Field(0.05, gt=0, description="Gauss-Newton: correspondence gate (m)")
    min_model_coverage: float = Field(0.3, ge=0, le=1, description="Gauss-Newton: skip the refinement when less "
                                      "than this fraction of the model view has alpha >= alpha_min")
    max_correction: float = Field(0.05, gt=0, description="keep the coarse pose when the refinement moves it "
                                                          "further than this (m)")
    acceptance_test: bool = Field(True, description="Gauss-Newton: per-frame acceptance test, keep the coarse pose "
                                  "unless the refinement lowers the robust hybrid residual against the model view")
    min_residual_gain: float = Field(0.0, ge=0, lt=1, description="Gauss-Newton: ... by at least this fraction of "
                                     "its value at the coarse pose")
    max_inlier_loss: float = Field(0.1, ge=0, le=1, description="Gauss-Newton: ... and keeps at least 1 - this of "
                                   "the coarse pose's correspondences")
    debias_view: bool = Field(True, description="Gauss-Newton: place each model view where its own keyframe "
                              "aligns to it (removes the view's offset from its keyframe, up to max_view_bias)")
    max_view_bias: float = Field(0.005, gt=0, description="Gauss-Newton: a model view is not used when its own "
                                 "keyframe, aligned to it, moves more than this (m): the map disagrees with it")
    adam_iterations: int = Field(20, ge=1, description="Adam: maximum iterations at the finest level")
    lr_rotation: float = Field(2e-3, gt=0, description="Adam step on the rotation (rad)")
    lr_translation: float = Field(2e-3, gt=0, description="Adam step on the translation (m)")
    lambda_color: float = Field(0.5, ge=0, le=1, description="Adam: λ_c, weight of colour vs depth L1 (eq. 3/5)")
    alpha_power: float = Field(4.0, ge=0, description="Adam: soft alpha mask M_α = alpha^p")
    alpha_min: float = Field(0.9, ge=0, le=1, description="pixels rendered with alpha below this are ignored")
    inlier_k: float = Field(20.0, gt=0, description="Adam: M_in drops pixels whose error exceeds k x median error")
    normalise_by_alpha: bool = Field(False, description="Adam: compare colour / alpha and depth / alpha with the "
                                     "input instead of the un-normalised renders")
    converge_rot: float = Field(2e-5, gt=0, description="Adam: stop when a step rotates less than this (rad) ...")
    converge_trans: float = Field(2e-5, gt=0, description="... and translates less than this (m) for `patience` "
                                                          "steps")
    patience: int = Field(3, ge=1, description="Adam: steps below the convergence thresholds before stopping")
    min_relative_gain: float = Field(0.1, ge=0, lt=1, description="Adam: keep the coarse pose unless the refined "
                                     "one lowers the tracking loss by this fraction")


class KeyframeConfig(_Section):
    every: int = Field(5, ge=1, description="a keyframe at least every N frames")
    max_translation: float = Field(0.15, gt=0, description="... or when it moved this far from the last keyframe (m)")
    max_rotation_deg: float = Field(10.0, gt=0, description="... or rotated this much (degrees)")


class MappingConfig(_Section):
    max_width: int = Field(0, ge=0, description="width of the mapping renders; 0 (default) = the working "
                                                "resolution (image.max_width). A lower width maps faster and "
                                                "coarser; evaluation is at the working and input resolution")
    iterations: int = Field(30, ge=0, description="optimisation iterations per new keyframe")
    first_iterations: int = Field(100, ge=0, description="iterations for a submap's first keyframe")
    current_keyframe_fraction: float = Field(0.4, ge=0, le=1, description="share of iterations on the newest keyframe")
    alpha_seed: float = Field(0.95, ge=0, le=1, description="α_min: seed Gaussians where rendered alpha is below "
                                                           "this")
    seed_stride: int = Field(1, ge=1, description="one seed per stride x stride pixels in sparse regions")
    seed_without_depth: bool = Field(True, description="also seed the large regions without valid depth (windows, "
                                     "sky, beyond the sensor's range) at the farthest valid depth nearby or of the "
                                     "frame (slam.dense.mapping.mapper.fallback_depth); off leaves them empty, "
                                     "rendered black")
    no_depth_min_region: float = Field(0.01, ge=0, le=1, description="... regions (>= 3 px across) covering at "
                                       "least this fraction of the image; smaller holes are left to the "
                                       "Gaussians around them")
    max_new_gaussians: int = Field(30000, ge=1, description="at most this many Gaussians seeded per keyframe")
    init_opacity: float = Field(0.5, gt=0, lt=1, description="opacity of a new Gaussian")
    init_scale_factor: float = Field(2.0, gt=0, description="initial radius = factor x stride x pixel footprint / "
                                                            "2 (metres at the pixel's depth)")
    lambda_color: float = Field(0.5, ge=0, le=1, description="λ_c of eq. 3")
    alpha_power: float = Field(0.0, ge=0, description="soft alpha mask M_α = alpha^p (0 = no mask)")
    inlier_k: float = Field(50.0, gt=0, description="M_in: drop pixels whose error exceeds k x median error")
    lr_means: float = Field(5e-4, gt=0, description="metres per step (scaled by the scene depth)")
    lr_log_scales: float = Field(5e-3, gt=0, description="Adam step on the log scales")
    lr_quats: float = Field(1e-3, gt=0, description="Adam step on the rotation quaternions")
    lr_opacities: float = Field(5e-2, gt=0, description="Adam step on the opacity logits")
    lr_colors: float = Field(2e-2, gt=0, description="Adam step on the colours (RGB in [0, 1])")
    prune_min_opacity: float = Field(0.05, ge=0, lt=1, description="Gaussians below this opacity are removed")
    prune_max_scale: float = Field(0.5, gt=0, description="Gaussians larger than this (m) are removed")
    isotropic_regulariser: float = Field(10.0, ge=0, description="penalty on scales far from their mean")
    seed: int = Field(0, description="seed of the keyframe sampling")


class ExposureConfig(_Section):
    """The photometric model of a real camera (slam.dense.mapping.exposure): an affine colour transform per
    keyframe (gain and offset per channel), fitted at each new keyframe against the map and optimised with it in
    mapping and in the final map refinement."""

    enabled: bool | Literal["auto"] = Field(
        "auto", description="model each keyframe's exposure and white balance. auto: watch the camera and switch the "
        "model on at the first keyframe whose fitted gain departs from the map's colours by more than "
        "auto_threshold beyond the previous keyframe's own fit to the map (a real camera's auto exposure; rendered "
        "data never does, and runs as with false, in real time too, where a map mapped for a few iterations reads "
        "as a gain on every keyframe); true: "
        "from the first keyframe; false: fit the map's colours to every image as it is (docs/decisions/0011)")
    auto_threshold: float = Field(0.05, gt=0, description="auto: the |log gain| in any channel (0.05 = 5 %) at "
                                  "which a keyframe's fit switches the model on; fits on rendered data stay "
                                  "within 0.015 (Redwood), a HoloLens 2 passes 0.1 at its second keyframe")
    lr: float = Field(5e-3, gt=0, description="Adam step on a keyframe's log gains and offsets")
    regulariser: float = Field(1.0, ge=0, description="weight of the squared distance of a keyframe's exposure "
                               "from its value fitted when it was made (per step, beside eq. 3's loss)")
    min_pixels: int = Field(500, ge=10, description="fit a new keyframe's exposure on at least this many pixels "
                            "where the map's render and the image agree in depth; fewer keep the previous "
                            "keyframe's")
    revisit_radius: float = Field(2.0, ge=0, description="a submap's first keyframe is fitted against the "
                                  "previous submap and every earlier one whose origin lies within this distance "
                                  "(m): a revisit ties the colours back to the submaps that saw the place first "
                                  "(0: the previous submap only)")
    max_gain: float = Field(2.5, gt=1, description="a keyframe whose fitted gain differs from its predecessor's "
                            "by more than this factor in a channel (or whose image is black or white) is an "
                            "outlier: it keeps the previous exposure and its colour is left out of the loss")
    map_gauge: Literal["first", "median"] = Field(
        "first", description="the gauge of the map's own colours after the final map refinement (map.ply and the "
        "viewer show them at the keyframes' median exposure either way: slam.dense.mapping.exposure.for_display). "
        "first: the first keyframe's, which drifts over a long walk. median: the keyframes' median exposure per "
        "channel, exp(m) on every colour and -m on every log gain, which leaves each exposed render as it was "
        "except where a colour passes 1 and the rasteriser clips it (the trade-off on a real camera: "
        "docs/decisions/0011)")


class MapRefineConfig(_Section):
    """Server-side refinement of each component's merged map after the final pose-graph optimisation
    (slam.dense.mapping.refine_merged): the merged map optimised jointly over all keyframes."""

    iterations_per_keyframe: int = Field(32, ge=0, description="optimisation steps per keyframe of the component "
                                         "(one keyframe per step); 0 disables refinement")
    max_iterations: int = Field(4500, ge=0, description="cap on the steps per component (bounds the time: the "
                                "4,320 steps of a real office walk's 135 keyframes and 0.85 M Gaussians take "
                                "about 6.5 minutes on 2 CPU cores)")
    lr_scale: float = Field(2.0, gt=0, description="learning rates start at mapping's lr_* times this")
    lr_final_scale: float = Field(0.1, gt=0, le=1, description="the learning rates decay geometrically to this "
                                  "fraction of their start over the refinement's steps (1 = constant)")
    lambda_color: float = Field(0.9, ge=0, le=1, description="λ_c of eq. 3 in the refinement")
    isotropic_regulariser: float = Field(0.0, ge=0, description="mapping's penalty on anisotropic scales (0 = "
                                                                "off)")
    min_contribution: float = Field(0.2, ge=0, description="first drop Gaussians whose total blending weight is "
                                    "below this many pixels in every keyframe (copies hidden behind another "
                                    "submap's surface); 0 keeps all")
    overlap_cull: bool = Field(True, description="before refining, keep each surface point in one submap only: "
                               "the one whose keyframe observed it on its depth surface from closest "
                               "(slam.dense.mapping.overlap_cull)")
    overlap_depth_tolerance: float = Field(0.03, ge=0, description="a keyframe observes a Gaussian's centre when "
                                           "it lies within max(this (m), overlap_depth_tolerance_rel x depth) of "
                                           "the keyframe's depth at its pixel")
    overlap_depth_tolerance_rel: float = Field(0.02, ge=0, description="see overlap_depth_tolerance")
    view_margin: float = Field(0.15, ge=0, description="a step optimises the Gaussians whose centre projects into "
                                                       "the keyframe's image grown by this fraction per side")
    views: Literal["mapping", "small"] = Field("mapping", description="keyframe images the refinement fits: "
                                               "'mapping' = at the mapping resolution (agents keep them, "
                                               "w x h x 7 bytes per keyframe), 'small' = the loop-closure copies "
                                               "(submaps.keep_keyframe_width): faster, blurrier above that width")
    single_agent: bool = Field(True, description="`swarmsplat run` refines its one agent's merged map the same "
                               "way after the last frame (its submaps overlap as a team's do); false skips it")
    refine_poses: bool | Literal["auto"] = Field(
        "auto", description="also refine each keyframe's pose with the map (photometric bundle adjustment; each "
        "agent's first keyframe holds its gauge); the keyframes and the frames tracked after them then follow the "
        "refined poses (Keyframe.T_local_refined). auto: where the camera's exposure model is on (a keyframe of the "
        "map has an exposure: a real camera, exposure.enabled), off elsewhere (on rendered and generated data it "
        "raised the map and moved the trajectory away from its ground truth; docs/decisions/0021)")
    lr_pose_rotation: float = Field(1e-3, gt=0, description="Adam step on a keyframe's rotation (rad)")
    lr_pose_translation: float = Field(3e-4, gt=0, description="Adam step on a keyframe's translation (m)")
    exposure_regulariser: float = Field(0.01, ge=0, description="weight of each keyframe's exposure prior in "
                                        "the refinement (exposure.regulariser is mapping's): the refinement, "
                                        "which sees every keyframe, settles the exposures that mapping's "
                                        "few views fitted (docs/decisions/0023)")
    exposure_lr: float = Field(0.02, gt=0, description="Adam step on a keyframe's log gains and offsets in the "
                                "refinement (exposure.lr is mapping's)")
    optimizer: Literal["selective", "adam"] = Field("adam", description="'selective': Adam on the "
                                                    "Gaussians of each step's view only, with per-Gaussian bias "
                                                    "correction (slam.dense.mapping.selective_adam); 'adam': torch's Adam over "
                                                    "the whole merged map every step")
    seed: int = Field(0, description="seed of the keyframe order")
    view_cache_mb: float = Field(64.0, ge=0, description="decoded keyframe images the refinement keeps between "
                                 "steps (MB, float tensors, least recently used dropped first); the rest stay as "
                                 "stored (PNG) and are decoded at each step (0 = decode every time)")
    region_gaussians: int = Field(1048576, ge=0, description="refine a map of more Gaussians than this (after "
                                  "the overlap cull and the hidden-copy cull) region by region: split in space "
                                  "into regions of at most this many, each optimised over the keyframes that see "
                                  "it with the rest of the map "
                                  "drawn frozen, so the optimiser's memory is a region's "
                                  "(slam.dense.mapping.refine_regions); 0 = the whole map at once")


class SubmapConfig(_Section):
    d_max: float = Field(0.5, gt=0, description="new submap when the keyframe is this far from the submap's first (m)")
    theta_max_deg: float = Field(30.0, gt=0, description="... or rotated this much (degrees)")
    max_keyframes: int = Field(40, ge=1, description="... or the submap has this many keyframes (bounds memory)")
    keep_keyframe_width: int = Field(160, ge=16, description="stored keyframes (for loop closure) kept at this width")
    storage: Literal["compact", "float32"] = Field("compact", description="finished submaps' Gaussians kept as: "
                                                   "'compact' (means 16-bit in the submap's box, the rest 8-bit, "
                                                   "zlib; about 12 bytes each, slam.dense.submap_codec) or "
                                                   "'float32' (as optimised, 56 bytes each)")
    offload: bool = Field(True, description="a run with an output folder writes each finished submap's Gaussians "
                          "to submaps/NNNN.bin there (in the `storage` form) and drops them from memory; they are "
                          "read back for the final refinement and map.ply")
    offload_keyframes: bool = Field(True, description="a run with an output folder writes each finished "
                                    "submap's keyframe images (packed losslessly: the loop-closure copy and, when "
                                    "the final refinement uses them, the mapping-resolution one) to keyframes/ "
                                    "there and drops them from memory; loop closure and the refinement read them "
                                    "back (about 0.4 MB per keyframe at 320x240)")
    prune_min_contribution: float = Field(0.0, ge=0, description="when a submap is finished, drop its Gaussians "
                                          "whose total blending weight in every one of its keyframes' renders is "
                                          "below this (pixels); 0 keeps all")


class LoopClosureConfig(_Section):
    enabled: bool = Field(True, description="look for loop closures (a team: the server looks for them)")
    descriptor: Literal["thumbnail", "bow", "vlad", "xfeat-vlad", "auto"] = Field(
        "auto", description="keyframe descriptor from registration.place_recognition; 'thumbnail' needs no "
                            "weights or vocabulary, 'bow'/'vlad' need `vocabulary`; 'xfeat-vlad' (VLAD over XFeat) "
                            "uses the vocabulary shipped with the package unless `vocabulary` says otherwise; 'auto' "
                            "= xfeat-vlad, or the thumbnail where XFeat cannot run (not installed, keyframe copies "
                            "under 32 pixels a side)")
    descriptor_width: int = Field(320, ge=32, description="width (pixels) of the keyframe view the descriptor "
                                  "describes: the mapping-resolution copy downsampled to it (never upsampled)")
    vocabulary: str | None = Field(None, description="vocabulary (.npz) for descriptor bow/vlad/xfeat-vlad; "
                                   "xfeat-vlad: null = the shipped generic one, 'train' = trained from the agent's "
                                   "first `vocabulary_keyframes` keyframes")
    vocabulary_keyframes: int = Field(8, ge=2, description="xfeat-vlad with vocabulary 'train': keyframes the agent "
                                                           "trains it from (described once it is trained)")
    candidates: Literal["descriptor", "pose", "both"] = Field(
        "both", description="where candidates come from: the keyframe descriptor (top_k above tau_sim), the tracked "
                            "poses (pose_top_k by view overlap; GRAND-SLAM eq. 6), or both")
    top_k: int = Field(3, ge=1, description="descriptor candidates per keyframe")
    pose_top_k: int = Field(2, ge=0, description="pose candidates per keyframe (best view overlap first)")
    pose_max_distance: float = Field(1.0, gt=0, description="pose candidates: camera centres at most this far (m)")
    pose_max_angle_deg: float = Field(45.0, gt=0, le=180, description="... and viewing directions at most this apart")
    pose_min_overlap: float = Field(0.3, ge=0, le=1, description="... and at least this fraction of the query's "
                                    "depth pixels reprojected into the match with consistent depth")
    pose_max_checked: int = Field(16, ge=1, description="pose candidates: the view overlap is computed for at most "
                                  "this many keyframes, the closest in position plus angle (1 m per radian) first")
    tau_sim: float | None = Field(None, ge=-1, le=1, description="cosine similarity gate of a descriptor "
                                  "candidate; null = none (the top_k best are verified)")
    min_index_gap: int = Field(20, ge=1, description="Δ_min: candidates at least this many frames apart")
    min_baseline: float = Field(0.0, ge=0, description="optional spatial gap between keyframe poses (m)")
    fitness_min: float = Field(0.5, ge=0, le=1, description="τ_f: accept when ICP fitness is above")
    rmse_max: float = Field(0.03, gt=0, description="τ_ρ: accept when ICP inlier RMSE is below (m)")
    icp_max_distance: float = Field(0.05, gt=0, description="ICP correspondence distance (m)")
    max_correction: float = Field(0.5, gt=0, description="reject loops that move the pose by more than this (m)")
    global_fallback: bool = Field(False, description="restart a candidate that fails the gates from FPFH + RANSAC "
                                  "(~1-3 s CPU each) instead of rejecting it")
    descriptor_min_overlap: float = Field(0.1, ge=0, le=1, description="without global_fallback, a descriptor "
                                          "candidate is registered only when the tracked poses make this fraction "
                                          "of the query's depth pixels land in the match view (0 = always)")
    cloud_route: bool = Field(True, description="within one agent and between agents already in one frame: when "
                              "keyframe ICP from the current pose accepted none of a keyframe's candidates, register "
                              "the keyframes' local maps (a window of keyframes each, fused with depth; "
                              "slam.dense.loops.local_clouds) by ICP from the same start for the candidates that "
                              "failed its gates, and accept a loop only if a render of the matched submaps from the "
                              "result agrees with the query's view; its information adds both windows' tracking "
                              "spread (wide revisits, which keyframe ICP cannot close)")
    cloud_window: int = Field(6, ge=0, description="cloud route: keyframes within this many keyframe ids of the "
                              "candidate's, on each side, make its local map")
    cloud_voxel: float = Field(0.08, gt=0, description="cloud route: voxel grid (m); normals within 2.5 voxels, FPFH "
                               "within 5, ICP correspondences within 1")
    cloud_min_fitness: float = Field(0.2, ge=0, le=1, description="cloud route: at least this fraction of the query "
                                     "window's points within one voxel of the match window's after ICP ...")
    cloud_max_rmse: float = Field(0.06, gt=0, description="... with an RMSE of at most this (m)")
    cloud_per_keyframe: int = Field(2, ge=0, description="cloud route: at most this many candidates of one query "
                                    "keyframe take it (best first), which bounds its cost per keyframe")
    render_min_covisible: float = Field(0.15, ge=0, le=1, description="verification by rendering "
                                        "(slam.dense.loops.render_check): the render covers at least this fraction "
                                        "of the query's valid depth pixels ...")
    render_min_agree: float = Field(0.5, ge=0, le=1, description="... agrees in depth (5 cm + 3 %) on at least this "
                                    "fraction of them ...")
    render_max_violate: float = Field(0.15, ge=0, le=1, description="... lies in front of the observed surface (by "
                                      "10 cm + 5 %) on at most this fraction (a loop that joins two agents' frames: "
                                      "server.join_max_violate, if stricter) ...")
    render_max_photometric: float = Field(0.12, gt=0, description="... and differs in colour, after a gain and offset "
                                          "per channel, by at most this mean absolute error (0-1 scale)")
    solver: Literal["incremental", "batch"] = Field(
        "incremental", description="pose-graph optimisation after a loop: 'incremental' (iSAM2 keeps the graph and "
                                   "re-solves only the part the new edges touch; the same optimum to within 0.03 "
                                   "mm) or 'batch' (Levenberg-Marquardt over every keyframe each time)")
    information: Literal["registration", "fixed"] = Field(
        "registration", description="edge information (eqs. 10-11): from each registration's information matrix, "
                                    "RMSE and correspondence count (tracking edges chain their frame-to-frame steps; "
                                    "slam.dense.loops.edge_information), or 'fixed' = the sigmas below for every edge")
    information_points: float = Field(25.0, gt=0, description="effectively independent residuals per registration "
                                      "(dense residuals are correlated; sets the overall confidence, the same for "
                                      "tracking and loop edges)")
    odometry_sigma_rot: float = Field(0.01, gt=0, description="edge std (rad) with information: fixed")
    odometry_sigma_trans: float = Field(0.01, gt=0, description="edge std (m) with information: fixed")
    residual_max_trans: float = Field(0.03, gt=0, description="after each optimisation, a loop whose residual "
                                      "exceeds this (m) ...")
    residual_max_deg: float = Field(1.5, gt=0, description="... or this (degrees) is rejected as inconsistent and "
                                    "the graph solved again")
    max_move_factor: float = Field(3.0, gt=0, description="an optimisation may move a keyframe at most this times "
                                   "the loops' disagreement with the current poses ...")
    max_move_slack: float = Field(0.05, ge=0, description="... plus this (m); otherwise it is not applied")


class KernelsConfig(_Section):
    backend: Literal["warp", "taichi"] = Field("warp", description="kernel backend (--kernels)")
    device: Literal["cpu", "cuda", "vulkan"] = Field("cpu", description="kernel device (--device; vulkan: taichi "
                                                                        "only)")
    torch_threads: int = Field(1, ge=0, description="torch intra-op threads (0 = torch's default)")
    malloc_mmap_threshold_kb: int = Field(0, ge=0, description="Linux (glibc): allocations of at least this "
                                          "many kB get pages of their own, returned to the system when freed "
                                          "(lower, flatter memory for a few tens of percent more CPU: "
                                          "slam.run.runtime.tame_allocator); 0 keeps glibc's adaptive rule. "
                                          "MALLOC_MMAP_THRESHOLD_ in the environment wins")
    malloc_trim: bool = Field(True, description="Linux (glibc): hand the heap's free pages back to the system each "
                              "time a submap is finished (kernels.memory.trim_heap), so a long mission's "
                              "memory does not creep up with its submaps")
