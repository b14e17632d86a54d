"""An agent's state to its ROS 2 topics (slam.io.ros2.AgentTopics), followed after every step.

After each step: the frame's pose and TF (if it was tracked); the keyframe path when a keyframe was added, the pose
graph was optimised or the caller says the map moved (a team server's correction); each submap that finished
since, as a point cloud of its Gaussian centres with their colour (at most `submap_points`, every k-th; with the
camera's exposure model on, as map.ply shows them: at the keyframes' median exposure); the
accepted loops when there are more; and every `map_period_s` seconds the whole map (at most `map_points`): the
finished submaps' points as they were sent, moved to where their frames are now, and the active submap's. Only
references and small copies are taken on the caller's thread; the clouds are read, decimated and sent by the
publishers' worker. `publish_s` keeps the caller's time per step (what publishing adds to tracking).
"""

from __future__ import annotations

import time

import numpy as np

from swarmsplat.slam.dense.mapping.exposure import display_gain


def local_points(submap, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [N, 3] float32 in the submap's frame, rgb [N, 3] uint8) of every k-th Gaussian centre of `submap`
    (anything with len() and .params), k the smallest stride that leaves at most `max_points`."""
    k = max(1, -(-len(submap) // max(1, max_points)))
    p = submap.params
    c = p.colors.detach()[::k].cpu().numpy()
    return (p.means.detach()[::k].cpu().numpy().astype(np.float32),
            np.clip(np.rint(c * 255.0), 0, 255).astype(np.uint8))


class PointCache:
    """Clouds of Gaussian centres for the publishing thread: a finished submap's points are read (and decoded, if
    it is stored compactly) once, then only moved to where its frame is now."""

    def __init__(self, submap_points: int = 20_000):
        self.submap_points = int(submap_points)
        self._local: dict = {}

    def local(self, key, submap, finished: bool = True) -> tuple[np.ndarray, np.ndarray]:
        if key in self._local:
            return self._local[key]
        pts = local_points(submap, self.submap_points)
        if finished:
            self._local[key] = pts
        return pts

    def world(self, parts: list[tuple], max_points: int, gain: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """(xyz [N, 3] float32 in the world, rgb [N, 3] uint8) of [(key, submap, T_world_local, finished)], every
        k-th point of their union so that at most `max_points` remain; colours times `gain` [3] (the keyframes'
        median exposure, slam.dense.mapping.exposure.display_gain: as map.ply shows them; None: as they are)."""
        xyz, rgb = [], []
        for key, submap, T, finished in parts:
            if len(submap):
                p, c = self.local(key, submap, finished)
                xyz.append((p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
                rgb.append(c)
        if not xyz:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        xyz, rgb = np.concatenate(xyz), np.concatenate(rgb)
        k = max(1, -(-len(xyz) // max(1, max_points)))
        xyz, rgb = xyz[::k], rgb[::k]
        if gain is not None:
            rgb = np.clip(np.rint(rgb * np.asarray(gain, np.float32)), 0, 255).astype(np.uint8)
        return xyz, rgb


def accepted_loops(agent) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(p_i, p_j, "intra") of the agent's accepted loops, at its keyframes' current positions."""
    if not agent.keyframes:
        return []
    T = agent.keyframe_world_poses()
    return [(T[c.query_kf][:3, 3], T[c.match_kf][:3, 3], "intra") for c in agent.loops.log
            if c.accepted and c.query_kf < len(T) and c.match_kf < len(T)]


class AgentFeed:
    """Publishes `agent`'s progress on `topics` (see the module docstring)."""

    def __init__(self, topics, *, map_period_s: float = 10.0, map_points: int = 100_000,
                 submap_points: int = 20_000, clock=time.monotonic):
        self.topics, self.clock = topics, clock
        self.map_period_s, self.map_points = float(map_period_s), int(map_points)
        self.points = PointCache(submap_points)  # used on the publishing thread only
        self._state = None
        self._submaps_sent = 0
        self._loops = 0
        self._map_at = clock()
        self.publish_s: list[float] = []

    def step(self, agent, t: float, rec, *, moved: int = 0) -> None:
        """After `agent` stepped on the frame at time t (rec: its FramePose, None if untracked); `moved` changes
        when something outside the agent moved its map (a team server's corrections)."""
        t0 = time.perf_counter()
        with self.topics.held():  # the publishing threads start on what is queued once this returns
            if rec is not None:
                self.topics.pose(t, agent.gmap.submaps[rec.submap_id].T_world_local @ rec.T_local_cam)
            self._follow(agent, t, moved)
            if self.map_period_s > 0 and self.clock() - self._map_at >= self.map_period_s:
                self.whole_map(agent, t)
        self.publish_s.append(time.perf_counter() - t0)

    def _follow(self, agent, t: float, moved: int) -> None:
        state = (len(agent.keyframes), agent.loops.optimisations, moved)
        changed = state != self._state and bool(agent.keyframes)
        if changed:
            self._state = state
            self.topics.path(np.array([k.timestamp for k in agent.keyframes]), agent.keyframe_world_poses())
        finished = len(agent.gmap.submaps) - 1  # all but the active one
        gain = display_gain(agent.keyframes) if self._submaps_sent < finished else None  # once per step
        while self._submaps_sent < finished:
            s = agent.gmap.submaps[self._submaps_sent]
            part = [(s.id, s, s.T_world_local.copy(), True)]
            self.topics.cloud("submap", t, lambda part=part, gain=gain: self.points.world(
                part, self.points.submap_points, gain))
            self._submaps_sent += 1
        if not changed and self._loops >= 0:  # loops are accepted with a keyframe, moved by an optimisation
            return
        n_loops = sum(1 for c in agent.loops.log if c.accepted)
        if n_loops != self._loops:
            self._loops = n_loops
            self.topics.loops(t, accepted_loops(agent))

    def whole_map(self, agent, t: float) -> None:
        """The whole map now (queued: the newest request wins)."""
        self._map_at = self.clock()
        last = len(agent.gmap.submaps) - 1
        part = [(s.id, s, s.T_world_local.copy(), i < last) for i, s in enumerate(agent.gmap.submaps)]
        gain = display_gain(agent.keyframes)
        self.topics.cloud("map", t, lambda: self.points.world(part, self.map_points, gain))

    def finish(self, agent, t: float, timeout: float = 10.0) -> None:
        """At the end: the last path, submaps and loops, the whole map, and wait (up to `timeout` s) until sent."""
        self._loops = -1  # the loops once more, even none: a subscriber learns the final state
        self._follow(agent, t, -1)
        self.whole_map(agent, t)
        self.topics.flush(timeout)
