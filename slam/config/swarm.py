"""The `swarm` section: FLOCC-SLAM's decentralised loop closing over the robots of a monocular dataset
(`swarmsplat swarm` and `swarmsplat robot`; slam.run.swarm builds the robots' NodeConfig and SolveConfig from it);
and the `pairs` section: the same front-end over every keyframe pair of a dataset (`swarmsplat pairs`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _FrontEnd(BaseModel):
    """Place recognition and image-pair registration (slam.flocc.frontend), shared by `swarm` and `pairs`."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    strict: bool = Field(False, description="stop at the first unreadable keyframe image; false leaves it out with "
                                            "a warning and lists it under skipped_frames in the metrics")
    place: str = Field("bow", description="place recognition: bow, vlad, xfeat-vlad, cosplace or netvlad")
    place_checkpoint: str | None = Field(None, description="weights of cosplace / netvlad, or a bow / vlad "
                                                           "vocabulary .npz; null trains the vocabulary on the "
                                                           "dataset's keyframes")
    backend: str = Field("classical", description="pair registration: classical, xfeat, mast3r or lightglue")
    checkpoint: str | None = Field(None, description="weights of the pair backend (mast3r)")
    device: Literal["cpu", "cuda"] = Field("cpu", description="torch device of the learned backends")
    r_thr: float | None = Field(None, ge=0, description="correspondence-ratio gate R_thr of eq. 1; null: the pair "
                                                       "backend's default (slam.flocc.frontend.default_r_thr)")
    k: float | None = Field(None, gt=0, description="logistic steepness k of eq. 2; null: the graph's default")


class SwarmConfig(_FrontEnd):
    """FLOCC-SLAM's robots: keyframes, schedule, front-end, network and pose graph."""

    stride: int = Field(4, ge=1, description="every stride-th frame of a robot is a keyframe")
    schedule: str | None = Field(None, description="rendezvous schedule YAML (slam.flocc.swarm.rendezvous); "
                                                   "null: pairs meet while recording, everyone at the end")
    threshold: float = Field(0.1, ge=-1, le=1, description="cosine similarity a loop candidate needs")
    # network
    neighbour_timeout: int = Field(3, ge=1, description="ticks without a hello before a robot counts as out of "
                                                        "range")
    resend: int = Field(4, ge=1, description="ticks before something a neighbour still lacks is sent again")
    end_timeout: float = Field(60.0, gt=0, description="seconds the end protocol may run after the schedule's last "
                                                      "tick (robots go on exchanging until every robot in range "
                                                      "holds the final estimate); past it they stop and report the "
                                                      "robots not heard from")
    port_base: int = Field(17447, description="Zenoh runs: robot K listens on TCP port port_base + K")
    # back-end
    formulation: Literal["is", "ss", "base", "shared"] = Field(
        "is", description="scale variables of the up-to-scale loops: independent (is), smoothed (ss), none (base) "
                          "or one shared (graph.formulations)")
    solver: Literal["lm", "gnc", "distributed"] = Field(
        "lm", description="Levenberg-Marquardt or GNC (rejects inconsistent loops) on the elected robot, or "
                          "distributed: every robot solves its own part (formulations base, is, ss)")
    uniform_noise: bool = Field(False, description="one noise for every factor, confidences ignored (the "
                                                   "Swarm-SLAM-like baseline)")
    odo_sigma_rot: float = Field(0.01, gt=0, description="odometry edge std (rad)")
    odo_sigma_trans: float = Field(0.02, gt=0, description="odometry edge std (m)")
    loop_sigma_rot: float = Field(0.05, gt=0, description="loop edge std at confidence 1 (rad)")
    loop_sigma_trans: float = Field(0.1, gt=0, description="loop edge std at confidence 1 (m, unit-scale "
                                                           "translation)")


class PairsConfig(_FrontEnd):
    """`swarmsplat pairs`: every keyframe's nearest neighbours among the other agents' keyframes, registered and
    scored."""

    stride: int = Field(1, ge=1, description="every stride-th frame of an agent is a keyframe")
    threshold: float | None = Field(0.1, ge=-1, le=1, description="cosine similarity a candidate needs; null: "
                                                                 "every nearest neighbour")
    top_k: int = Field(1, ge=1, description="neighbours per keyframe")
