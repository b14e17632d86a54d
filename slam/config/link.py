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
        "float32", description="encoding of a finished submap's Gaussians on the link: float32 (exact), float16 "
                               "(means stay float32) or compact (submaps.storage's compact form: means 16-bit in "
                               "the submap's box, the rest 8-bit, zlib; about 12 of float32's 56 bytes)")
    images: Literal["lossless", "compact"] = Field(
        "lossless", description="keyframe images on the link: lossless PNG (the server sees the agent's frames bit "
                                "for bit), or compact: JPEG colour (jpeg_quality) and depth rounded to millimetres")
    jpeg_quality: int = Field(90, ge=1, le=100, description="JPEG quality of images: compact")
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
