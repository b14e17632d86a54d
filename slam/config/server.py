"""The `server` section: the GRAND-SLAM team server's settings (slam.dense.team.server.Server); a team run writes
it as server.yaml too."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class ServerConfig(BaseModel):
    """Settings of the server role. The registration gates (τ_f, τ_ρ, ICP distance, max correction) are the
    agents' `loop_closure` section, so intra and inter loops pass the same tests."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    intra_loops: bool = Field(True, description="look for loops inside each agent's own keyframes")
    inter_loops: bool = Field(True, description="look for loops between agents")
    descriptor: Literal["agent", "bow", "vlad", "xfeat-vlad"] = Field(
        "agent", description="inter-agent place descriptor: the agent's own keyframe descriptor, or a bag of "
                             "words / VLAD over RootSIFT (registration.place_recognition) with `vocabulary`, or "
                             "VLAD over XFeat (from the cached keyframe encodings, with the shipped generic "
                             "vocabulary unless `vocabulary` says otherwise)")
    vocabulary: str | None = Field(None, description="vocabulary .npz for descriptor bow / vlad / xfeat-vlad; "
                                   "xfeat-vlad: null = the shipped generic one, 'train' = trained from the first "
                                   "`vocabulary_keyframes` keyframes the server receives")
    vocabulary_keyframes: int = Field(8, ge=2, description="xfeat-vlad with vocabulary 'train': train it from "
                                                            "this many received keyframes (they are described then)")
    coarse: Literal["learned", "fpfh"] = Field(
        "learned", description="coarse start for agents not yet in one frame: 'learned' = XFeat + LighterGlue "
                               "matches lifted with depth and a RANSAC rigid fit (slam.dense.loops.learned_coarse; each "
                               "keyframe encoded once), 'fpfh' = FPFH + RANSAC (global_fallback)")
    learned_fallback: bool = Field(False, description="coarse learned: try FPFH + RANSAC when the learned guess "
                                                      "is not found")
    cloud_route: bool = Field(True, description="agents not yet in one frame: when the image route (learned guess, "
                              "then keyframe ICP) gives no verified pose, register the two keyframes' local maps as "
                              "point clouds (a window of keyframes each, fused with depth; "
                              "slam.dense.loops.local_clouds) by global registration and ICP; its window, voxel, "
                              "gates and budget are loop_closure's cloud_* and render_* keys")
    cloud_method: Literal["auto", "kiss-matcher", "fpfh-ransac"] = Field(
        "auto", description="the cloud route's global registration: KISS-Matcher, or Open3D's FPFH + RANSAC; 'auto' "
                            "= kiss-matcher where its wheel is installed (x86-64), else fpfh-ransac")
    render_check: Literal["cloud", "all", "off"] = Field(
        "cloud", description="verification by rendering (slam.dense.loops.render_check) of loops between agents "
                             "not yet in one frame: 'cloud' checks those from the cloud route, 'all' every one, 'off' "
                             "none (loop_closure's render_* gates)")
    join_max_violate: float = Field(0.06, ge=0, le=1, description="render check of a loop between agents not yet in "
                                    "one frame (a pose found without a start, which may align a repeated place): "
                                    "at most this fraction of the query's covered depth may lie in front of the "
                                    "observed surface (the stricter of this and loop_closure.render_max_violate, "
                                    "which loops from a tracked pose use)")
    same_frame_fallback: bool = Field(False, description="FPFH + RANSAC restart also for agents already in one "
                                      "frame when the start from their relative pose fails")
    tau_sim: float | None = Field(None, ge=-1, le=1, description="inter-agent cosine similarity gate; null = "
                                  "none: the top_k most similar keyframes are always verified")
    top_k: int = Field(2, ge=1, description="inter-agent descriptor candidates verified per new keyframe (best "
                                            "first): with loop_closure.pose_top_k, the verification budget per "
                                            "keyframe")
    coarse_width: int = Field(320, ge=32, description="width (pixels) at which the learned coarse start encodes "
                              "and lifts each keyframe (its mapping-resolution copy, downsampled), encoded once")
    join_min_loops: int = Field(2, ge=1, le=2, description="verified loops, mutually consistent, that two agents "
                                "not yet in one frame need before they are joined (1 = the first verified loop)")
    join_tolerance_trans: float = Field(0.15, gt=0, description="two join loops agree when the frame alignments "
                                        "they imply map both query keyframes within this distance (m)")
    join_tolerance_deg: float = Field(5.0, gt=0, description="... and differ by at most this rotation (degrees)")
    global_fallback: bool = Field(True, description="FPFH + RANSAC start when agents are not yet in one frame "
                                                    "(or the guess fails the gates)")
    solver: Literal["lm", "gnc"] = Field("lm", description="pose-graph solver; gnc rejects inconsistent loops")
    optimise_fraction: float = Field(0.05, ge=0, le=1, description="solve the team's pose graph after an accepted "
                                     "loop only once this fraction of the team's keyframes has arrived since the "
                                     "last solve (a join of two agents is solved at once; the end of the mission "
                                     "solves what waits): a long mission is then solved a number of times that "
                                     "grows with its logarithm, not with its length; 0 = after every keyframe with "
                                     "an accepted loop")
    loop_sigma_rot: float = Field(0.01, gt=0, description="loop-closure edge std (rad)")
    loop_sigma_trans: float = Field(0.01, gt=0, description="loop-closure edge std (m)")
