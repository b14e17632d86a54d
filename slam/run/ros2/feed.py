"""An agent's state to its ROS 2 topics (slam.io.ros2.AgentTopics), followed after every step.

After each step: the frame's pose and TF (if it was tracked); the keyframe path when a keyframe was added, the pose
graph was optimised or the caller says the map moved (a team server's correction); each submap that finished
since, as a point cloud of its Gaussian centres with their colour (at most `submap_points`, every k-th); the
accepted loops when there are more; and every `map_period_s` seconds the whole map (at most `map_points`). Only
references and small copies are taken on the caller's thread; the clouds are read, decimated and sent by the
publishers' worker. `publish_s` keeps the caller's time per step (what publishing adds to tracking).
"""

from __future__ import annotations

import time

import numpy as np


def gaussian_points(submaps: list[tuple[object, np.ndarray]], max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [N, 3] float32 in the world, rgb [N, 3] uint8) of the Gaussian centres of [(submap, T_world_local)],
    at most `max_points` over all, each submap's share in proportion to its size (every k-th Gaussian)."""
    sizes = np.array([len(s) for s, _ in submaps], float)
    total = max(1.0, sizes.sum())
    xyz, rgb = [], []
    for (s, T), n in zip(submaps, sizes):
        if n == 0:
            continue
        k = max(1, int(np.ceil(total / max(1, max_points))))
        p = s.params
        local = p.means.detach()[::k].cpu().numpy().astype(np.float64)
        xyz.append((local @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
        c = p.colors.detach()[::k].cpu().numpy()
        rgb.append(np.clip(np.rint(c * 255.0), 0, 255).astype(np.uint8))
    if not xyz:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    return np.concatenate(xyz), np.concatenate(rgb)


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
        self.map_period_s, self.map_points, self.submap_points = float(map_period_s), int(map_points), \
            int(submap_points)
        self._state = None
        self._submaps_sent = 0
        self._loops = 0
        self._map_at = clock()
        self.publish_s: list[float] = []

    def step(self, agent, t: float, rec, *, moved: int = 0) -> None:
        """After `agent` stepped on the frame at time t (rec: its FramePose, None if untracked); `moved` changes
        when something outside the agent moved its map (a team server's corrections)."""
        t0 = time.perf_counter()
        if rec is not None:
            self.topics.pose(t, agent.gmap.submaps[rec.submap_id].T_world_local @ rec.T_local_cam)
        with self.topics.held():  # the worker starts on what is queued once this returns
            self._follow(agent, t, moved)
            if self.map_period_s > 0 and self.clock() - self._map_at >= self.map_period_s:
                self.whole_map(agent, t)
        self.publish_s.append(time.perf_counter() - t0)

    def _follow(self, agent, t: float, moved: int) -> None:
        state = (len(agent.keyframes), agent.loops.optimisations, moved)
        if state != self._state and agent.keyframes:
            self._state = state
            self.topics.path(np.array([k.timestamp for k in agent.keyframes]), agent.keyframe_world_poses())
        finished = len(agent.gmap.submaps) - 1  # all but the active one
        while self._submaps_sent < finished:
            s = agent.gmap.submaps[self._submaps_sent]
            part = [(s, s.T_world_local.copy())]
            self.topics.cloud("submap", t, lambda part=part: gaussian_points(part, self.submap_points))
            self._submaps_sent += 1
        n_loops = sum(1 for c in agent.loops.log if c.accepted)
        if n_loops != self._loops:
            self._loops = n_loops
            self.topics.loops(t, accepted_loops(agent))

    def whole_map(self, agent, t: float) -> None:
        """The whole map now (queued: the newest request wins)."""
        self._map_at = self.clock()
        part = [(s, s.T_world_local.copy()) for s in agent.gmap.submaps]
        self.topics.cloud("map", t, lambda: gaussian_points(part, self.map_points))

    def finish(self, agent, t: float, timeout: float = 10.0) -> None:
        """At the end: the last path, submaps and loops, the whole map, and wait (up to `timeout` s) until sent."""
        self._loops = -1  # the loops once more, even none: a subscriber learns the final state
        self._follow(agent, t, -1)
        self.whole_map(agent, t)
        self.topics.flush(timeout)
