"""The server's copy of an agent that runs elsewhere: an `Agent` that never tracks or maps, whose keyframes,
submaps, tracking edges and frame poses are filled in from what the agent sends (slam.run.team_link), so the
team server (slam.dense.team.server.Server), the map refinement and the results writers read it exactly as they
read an agent of the same process.

Its submap origins are the server's own: a new submap starts at the previous one's (possibly corrected) origin
composed with the offset the agent tracked, which is how the agent itself places it, and a tracking edge across
two submaps is taken from those origins as the agent takes it from its own (the same product, so the same bits). Everything is idempotent:
a keyframe, submap or frame received twice is kept once.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.agent import Agent, FramePose
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.loops.loop_closure import Edge
from swarmsplat.slam.dense.submaps import Keyframe, world_pose


class AgentMirror(Agent):
    """An agent known only from its messages (module docstring). `step` is not available."""

    def __init__(self, camera: PinholeCamera, cfg: SlamConfig | None = None, *, name: str = "agent"):
        super().__init__(camera, cfg, name=name)
        self._frames: dict[int, FramePose] = {}
        self.finished = False  # the agent said it is done (Done received)

    def step(self, *args, **kwargs):
        raise RuntimeError(f"{self.name}: a mirrored agent runs elsewhere; it cannot step here")

    def add_keyframe(self, kf_id: int, frame_index: int, timestamp: float, submap_id: int, T_local_cam: np.ndarray,
                     descriptor: np.ndarray | None, small, map_rgbd, odometry: tuple | None,
                     submap_start: np.ndarray | None, *, exposure: np.ndarray | None = None) -> Keyframe | None:
        """Keyframe `kf_id` (the next one: ids arrive in order) with its images (RGBD or PackedRGBD), tracking
        edge from the previous keyframe (T [4, 4], information [6, 6]) and, for a submap's first keyframe, the
        new submap's origin relative to the previous one, and its exposure as fitted when it was made
        (slam.dense.mapping.exposure; the server's map refinement optimises it from there). Returns the keyframe
        (None: already known)."""
        if kf_id < len(self.keyframes):
            return None
        if kf_id != len(self.keyframes):
            raise ValueError(f"{self.name}: keyframe {kf_id} before keyframe {len(self.keyframes)}")
        if submap_id == len(self.gmap.submaps):
            T = np.eye(4) if not self.gmap.submaps else self.gmap.active.T_world_local @ submap_start
            self.gmap.new_submap(T)
        elif submap_id != len(self.gmap.submaps) - 1:
            raise ValueError(f"{self.name}: keyframe {kf_id} in submap {submap_id}, the active one is "
                             f"{len(self.gmap.submaps) - 1}")
        kf = Keyframe(kf_id, frame_index, timestamp, submap_id, np.array(T_local_cam, dtype=np.float64), map_rgbd,
                      small, None if descriptor is None or not len(descriptor) else np.asarray(descriptor))
        if exposure is not None:
            kf.exposure, kf.exposure_prior = np.array(exposure, dtype=np.float64), np.array(exposure, dtype=np.float64)
        self.keyframes.append(kf)
        self.gmap.submaps[submap_id].keyframe_ids.append(kf.id)
        if odometry is not None:
            T = np.array(odometry[0])
            prev = self.keyframes[kf_id - 1]
            if prev.submap_id != kf.submap_id:  # across submaps: from the origins, as LoopCloser.add_keyframe does
                T = se3.project_rigid(se3.inverse(world_pose(self.gmap, prev)) @ world_pose(self.gmap, kf))
            self.loops.odometry.append(Edge(kf_id - 1, kf_id, T, np.array(odometry[1])))
        return kf

    def set_submap(self, submap_id: int, params: GaussianParams) -> None:
        """A finished submap's Gaussians (its local frame)."""
        self.gmap.submaps[submap_id].params = params

    def add_frames(self, records: list[FramePose]) -> None:
        """Tracked frame poses (any order, repeats ignored); `poses` stays in frame order."""
        n = len(self._frames)
        for r in records:
            self._frames.setdefault(int(r.frame_index), r)
        if len(self._frames) != n:
            self.poses = [self._frames[i] for i in sorted(self._frames)]

    def finish(self, tracking_s: float, mapping_s: float, frames: int, non_finite_dropped: int) -> None:
        """The agent's totals from its last message."""
        self.time.tracking, self.time.mapping, self.time.frames = tracking_s, mapping_s, frames
        self.mapper.non_finite_dropped = non_finite_dropped
        self.finished = True

    def skip(self, index: int, reason: str) -> None:
        """A frame the agent skipped (listed in metrics.json), without a warning here."""
        if int(index) not in self.time.skip_reasons:
            self.time.skipped.append(int(index))
            self.time.skip_reasons[int(index)] = reason
