"""The `runtime` section: how `swarmsplat run` feeds frames to the agent. Offline (the default) processes every
frame in turn; real time replays them at the sensor's rate, tracks what it can and maps beside it
(slam.run.realtime, docs/realtime.md)."""

from __future__ import annotations

from pydantic import Field

from .agent import _Section


class RuntimeConfig(_Section):
    """How frames reach the agent (`swarmsplat run`): offline, every frame in turn (default), or in real time: frames
    arrive at their timestamps or at `rate`, tracking takes each frame it can and emits its pose, mapping and loop
    closure run in a thread beside it (docs/realtime.md)."""

    realtime: bool = Field(False, description="real-time mode: frames arrive at the sensor's rate, a frame the "
                                              "tracker cannot take in time is dropped, mapping runs concurrently")
    rate: float = Field(0.0, ge=0, description="real time: frame rate of the replay (Hz); 0 = the dataset's "
                                               "timestamps")
    queue: int = Field(1, ge=1, description="real time: frames waiting for the tracker at most; an arrival at a "
                                            "full queue drops the oldest waiting frame")
    max_latency_ms: float = Field(0.0, ge=0, description="real time: the pose latency budget (ms): a waiting frame "
                                  "is dropped when its wait plus the expected time to its pose exceed it while a "
                                  "fresh frame's would not; 0 = one frame interval")
    skip_late_refinement: bool = Field(True, description="real time: when a frame's frame-to-model refinement "
                                       "would end after its latency budget (its median time), the coarse pose "
                                       "goes out instead; counted in metrics.json realtime.refinements_skipped")
    min_mapping_iterations: int = Field(5, ge=0, description="real time: mapping iterations a keyframe gets at "
                                        "least before it yields to the next keyframe")
    max_mapping_iterations: int = Field(0, ge=0, description="real time: iterations a keyframe gets at most while "
                                        "no keyframe waits (0 = mapping.iterations, mapping.first_iterations for a "
                                        "submap's first keyframe)")
    refine_owed: bool = Field(True, description="real time: after the stream, the final map refinement "
                              "(map_refine) also runs the mapping iterations real time cut short "
                              "(metrics.json realtime.refine_owed_iterations), so the map gets the optimisation "
                              "an offline run gives it; the map is ready that much later, the poses are not "
                              "affected")
    late_views: bool = Field(True, description="real time: a frame due to be a keyframe while mapping was busy "
                             "(deferred) is kept as a late view, at most one per keyframes.every frames, unless the "
                             "keyframe it waited for came within half that; after the stream the final map "
                             "refinement (map_refine, on mapping-resolution views) fits the merged map to these "
                             "views too, as to keyframes, and owes each the mapping.iterations an offline run would "
                             "have mapped it with (metrics.json realtime.late_views); they are not held-out views")
    mapping_nice: int = Field(5, ge=0, le=19, description="real time: how much the mapping worker lowers its "
                              "threads' priority (nice value added; Linux), so tracking gets the cores first; "
                              "0 = the same priority")
