"""The `link` section: how a GRAND-SLAM team talks when its agents and server run as separate processes
(`swarmsplat server`, `swarmsplat agent --server`, `swarmsplat run --processes`; slam.run.team_link)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class LinkConfig(BaseModel):
    """The agent-server link: what a finished submap's Gaussians are sent as, the agent's send queue, and the time
    limits of each side."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    gaussians: Literal["float32", "float16", "compact"] = Field(
        "compact", description="encoding of a finished submap's Gaussians on the link: float32 (exact), float16 "
                               "(means stay float32) or compact (submaps.storage's compact values: means mean_bits "
                               "within the submap's box, the rest 8-bit; Morton-ordered, lzma; about 9 of "
                               "float32's 56 bytes; slam.dense.submap_codec)")
    mean_bits: int = Field(14, ge=10, le=16, description="gaussians: compact: bits of each mean coordinate within "
                                                        "the submap's box (16: the stored values; fewer quantise "
                                                        "them again, e.g. 14: 0.3 mm steps in a 5 m box)")
    cull_gaussians: bool = Field(True, description="leave out of a finished submap the Gaussians the server's "
                                                   "overlap cull (map_refine.overlap_cull) drops anyway: those "
                                                   "another of the agent's keyframes observes from closer "
                                                   "(slam.dense.team.link_cull)")
    submap_delay: int = Field(1, ge=0, description="an agent sends a finished submap once this many later submaps "
                                                   "are finished too (all at its last frame), so the cull also "
                                                   "counts their keyframes; the server installs submaps at the end")
    images: Literal["lossless", "compact"] = Field(
        "compact", description="keyframe images on the link: lossless PNG of both copies (the server sees the "
                                "agent's frames bit for bit), or compact: each picture once, the colour of the "
                                "largest copy as JPEG (jpeg_quality) and the loop-closure copy's depth in "
                                "inverse-depth steps (depth_step_mm); the server makes the rest "
                                "(slam.run.team_link.images)")
    jpeg_quality: int = Field(94, ge=1, le=100, description="JPEG quality of images: compact (full-resolution "
                                                            "chroma)")
    depth_step_mm: float = Field(0.5, gt=0, le=100, description="images: compact: the depth step at 1 m (mm); it "
                                                                "grows with the square of the range, as a "
                                                                "structured-light sensor's does")
    map_views: bool = Field(True, description="send each keyframe's mapping-resolution copy too when the server "
                                              "refines the merged map on it (map_refine.views mapping); false: it "
                                              "refines on the loop-closure copies")
    queue_mb: float = Field(256.0, gt=0, description="an agent's unacknowledged keyframe images beyond this many MB "
                                                     "are dropped, oldest first (poses, edges and submaps are kept)")
    resend_s: float = Field(30.0, gt=0, description="an agent sends a message again when the server has not "
                                                   "acknowledged it within this many seconds")
    connect_timeout_s: float = Field(60.0, gt=0, description="an agent gives up when no server answers within this "
                                                             "many seconds of its start")
    agent_timeout_s: float = Field(120.0, gt=0, description="the server reports an agent lost, and finishes without "
                                                            "it, after this many seconds without a message from it")
    finish_timeout_s: float = Field(120.0, gt=0, description="after its last frame, an agent waits at most this many "
                                                             "seconds for the server to acknowledge everything")
    port_base: int = Field(17560, ge=1, le=65000, description="`run --processes` (and `server` without --listen): "
                                                              "the server listens on this TCP port (run --processes: "
                                                              "the first free one from it)")
