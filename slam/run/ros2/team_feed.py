"""The team server's state to its ROS 2 topics (slam.io.ros2.TeamTopics), followed while it serves.

Every agent's keyframe trajectory in its component's frame (the team's frame once the agents have met) after each
keyframe the server takes in and each optimisation; the accepted loops when there are more; the merged map of the
finished submaps every `map_period_s` seconds and at the end. Submaps are decoded and decimated on the publishers'
worker thread, never on the server's.
"""

from __future__ import annotations

import time

import numpy as np

from swarmsplat.slam.dense.mapping.exposure import display_gain
from .feed import PointCache


class _Received:
    """A finished submap as the server received it (decoded only when read)."""

    def __init__(self, data):
        self.data = data

    def __len__(self) -> int:
        return len(self.data.means)

    @property
    def params(self):
        return self.data.params()


class TeamFeed:
    """Publishes a ServerNode's team on `topics` (see the module docstring)."""

    def __init__(self, topics, *, map_period_s: float = 10.0, map_points: int = 200_000, clock=time.monotonic):
        self.topics, self.clock = topics, clock
        self.map_period_s, self.map_points = float(map_period_s), int(map_points)
        self.points = PointCache()  # used on the publishing thread only
        self._state = None
        self._loops = 0
        self._map_at = clock()
        self._map_state = None

    def step(self, node, *, now: float | None = None) -> None:
        """After the server node stepped: what changed since the last call."""
        team = node.team
        srv = team.server
        state = (srv.optimisations, tuple(len(ag.keyframes) for ag in team.agents))
        if state != self._state:  # loops are decided with a keyframe, moved by an optimisation
            self._state = state
            self.topics.trajectories({ag.name: (np.array([k.timestamp for k in ag.keyframes]),
                                                 self._global(srv, a) @ ag.keyframe_world_poses())
                                      for a, ag in enumerate(team.agents) if ag.keyframes})
            n_loops = sum(1 for r in srv.records if r.accepted)
            if n_loops != self._loops:
                self._loops = n_loops
                self.topics.loops(self._stamp(team), self._loop_edges(team))
        if self.map_period_s > 0 and self.clock() - self._map_at >= self.map_period_s:
            self.merged_map(node)

    @staticmethod
    def _global(srv, a: int) -> np.ndarray:
        return srv.slots[a].T_global_world

    @staticmethod
    def _stamp(team) -> float:
        return max((ag.keyframes[-1].timestamp for ag in team.agents if ag.keyframes), default=0.0)

    def _loop_edges(self, team) -> list:
        srv = team.server
        by_name = {ag.name: a for a, ag in enumerate(team.agents)}
        poses = {a: self._global(srv, a) @ ag.keyframe_world_poses() for a, ag in enumerate(team.agents)
                 if ag.keyframes}
        edges = []
        for r in srv.records:
            qa, ma = by_name.get(r.query_agent), by_name.get(r.match_agent)
            if r.accepted and qa in poses and ma in poses and r.query_kf < len(poses[qa]) \
                    and r.match_kf < len(poses[ma]):
                edges.append((poses[qa][r.query_kf][:3, 3], poses[ma][r.match_kf][:3, 3],
                              "intra" if qa == ma else "inter"))
        return edges

    def merged_map(self, node) -> None:
        """The finished submaps of every agent, in the team's frame (queued: the newest request wins)."""
        self._map_at = self.clock()
        team, srv = node.team, node.team.server
        part = []
        for a, p in enumerate(node.peers):
            sms = team.agents[a].gmap.submaps
            for sid, sd in sorted(p.submaps.items()):
                if sid < len(sms):
                    part.append(((a, sid, id(sd)), _Received(sd), self._global(srv, a) @ sms[sid].T_world_local,
                                 True))
        state = tuple((key, T.tobytes()) for key, _, T, _ in part)
        if part and state != self._map_state:  # nothing new: nothing sent again
            self._map_state = state
            gain = display_gain([kf for s in srv.slots for kf in s.agent.keyframes])  # as map.ply shows them
            self.topics.map(self._stamp(team), lambda: self.points.world(part, self.map_points, gain))

    def finish(self, node, timeout: float = 10.0) -> None:
        """At the end: the last trajectories and loops, the merged map, and wait (up to `timeout` s) until sent."""
        self._state, self._loops = None, -1
        self.step(node)
        self.merged_map(node)
        self.topics.flush(timeout)
