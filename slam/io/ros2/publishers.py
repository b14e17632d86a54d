"""What swarmsplat publishes to ROS 2, topic by topic, with the quality of service a ROS 2 driver would choose.

An agent NAME (AgentTopics):
  /swarmsplat/NAME/pose     geometry_msgs/PoseStamped       every tracked frame       reliable, volatile, depth 10
  /tf                       tf2_msgs/TFMessage              every tracked frame       reliable, volatile, depth 100
                            (map -> NAME/camera)
  /swarmsplat/NAME/path     nav_msgs/Path                   keyframes, after each     reliable, transient local, depth 1
                                                            new keyframe / optimisation
  /swarmsplat/NAME/submap   sensor_msgs/PointCloud2         each finished submap      reliable, volatile, depth 10
  /swarmsplat/NAME/map      sensor_msgs/PointCloud2         the whole map, slowly     reliable, transient local, depth 1
  /swarmsplat/NAME/loops    visualization_msgs/MarkerArray  accepted loops            reliable, transient local, depth 1
The team server (TeamTopics): /swarmsplat/team/<agent>/path per agent, /swarmsplat/team/map,
/swarmsplat/team/loops, the same types and QoS (volatile where the session has no timestamping, which a
transient-local publisher's cache needs: the team link's).

The caller's thread only queues (tens of microseconds): poses and TF are built and sent, every one in order, by
one thread; paths, clouds and markers by another, from a queue that keeps the newest of each (every finished
submap, up to 32 waiting), so a map message never holds up tracking, nor a pose. Poses and TF go at a higher Zenoh priority than clouds (a link sends them
first) and are dropped rather than wait for a congested link; the worker waits instead (what it sends arrives,
at no cost to tracking).
"""

from __future__ import annotations

import collections
import contextlib
import re
import threading
import time

import numpy as np

from . import messages as M
from .keys import Qos
from .types import store

POSE_QOS, TF_QOS, SUBMAP_QOS = Qos(depth=10), Qos(depth=100), Qos(depth=10)
LATEST_QOS = Qos(depth=1, transient_local=True)  # latched, as a map server's: a late subscriber gets the last one
TYPES = {"pose": "geometry_msgs/msg/PoseStamped", "tf": "tf2_msgs/msg/TFMessage", "path": "nav_msgs/msg/Path",
         "submap": "sensor_msgs/msg/PointCloud2", "map": "sensor_msgs/msg/PointCloud2",
         "loops": "visualization_msgs/msg/MarkerArray"}
QOS = {"pose": POSE_QOS, "tf": TF_QOS, "path": LATEST_QOS, "submap": SUBMAP_QOS, "map": LATEST_QOS,
       "loops": LATEST_QOS}
# Zenoh priorities: per-frame messages first, clouds last; the queued kinds are sent by the worker, which may wait
PRIORITY = {"pose": "DATA_HIGH", "tf": "DATA_HIGH", "path": "DATA", "loops": "DATA", "submap": "DATA_LOW",
            "map": "DATA_LOW"}
QUEUED = ("path", "submap", "map", "loops")


def ros_token(name: str) -> str:
    """`name` as one ROS name token (characters other than letters, digits and _ become _)."""
    t = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return t if t and not t[0].isdigit() else "_" + t


class _Lane:
    """A queue and the thread that empties it: `put(role, build)` queues `build()` -> message for topic `role`,
    keeping only the newest waiting one per role unless `keep_all` (then up to `max_waiting`, oldest out first)."""

    def __init__(self, name: str, send, max_waiting: int):
        self.send = send  # send(role, msg)
        self.fifo: collections.deque = collections.deque(maxlen=max_waiting)
        self.latest: dict = {}
        self.superseded: collections.Counter = collections.Counter()
        self.failed = 0
        self.cv = threading.Condition()
        self.busy = self.held = self.stop = False
        self.thread = threading.Thread(target=self._work, name=name, daemon=True)
        self.thread.start()

    def put(self, role: str, build, keep_all: bool) -> None:
        with self.cv:
            if keep_all:
                if len(self.fifo) == self.fifo.maxlen:
                    self.superseded[self.fifo[0][0]] += 1
                self.fifo.append((role, build))
            else:
                if role in self.latest:
                    self.superseded[role] += 1
                self.latest[role] = build
            if not self.held:
                self.cv.notify()

    def release(self) -> None:
        with self.cv:
            self.held = False
            self.cv.notify()

    def _work(self) -> None:
        while True:
            with self.cv:
                self.cv.wait_for(lambda: (self.fifo or self.latest) and not self.held or self.stop)
                if self.fifo:
                    role, build = self.fifo.popleft()
                elif self.latest:
                    role = next(iter(self.latest))
                    build = self.latest.pop(role)
                else:
                    return
                self.busy = True
            try:
                msg = build()
                if msg is not None:
                    self.send(role, msg)
            except Exception:  # noqa: BLE001 - a message that cannot be built or sent must not end the publishing
                self.failed += 1
            finally:
                with self.cv:
                    self.busy = False
                    self.cv.notify_all()

    def flush(self, timeout: float) -> bool:
        with self.cv:
            return self.cv.wait_for(lambda: not (self.fifo or self.latest or self.busy), timeout=timeout)

    def close(self) -> None:
        with self.cv:
            self.stop = True
            self.cv.notify_all()
        self.thread.join(timeout=2.0)


class Topics:
    """Publishers of one node, and two threads that build and send their messages: one for the per-frame messages
    (every one, in order), one for those that may wait (the newest of each; see _Lane). The caller's thread only
    queues. `stats()`: messages sent per topic, queued ones superseded by a newer one before they went, failures."""

    def __init__(self, node, topics: dict[str, str], *, frame: str = "map", max_waiting: int = 32):
        self.node, self.frame, self.ty = node, frame, store().types
        self.topics = dict(topics)
        self._pubs: dict[str, object] = {}
        self.sent: collections.Counter = collections.Counter()
        self._fast = _Lane("ros2-publish-frames", self._send, 1000)
        self._slow = _Lane("ros2-publish-maps", self._send, max_waiting)

    def _send(self, role: str, msg) -> None:
        self._pubs[role].put(msg)
        self.sent[role] += 1

    def publisher(self, role: str, kind: str | None = None):
        """The publisher of topic `role` (its type and QoS from `kind`, default the role up to a colon)."""
        if role not in self._pubs:
            kind = kind or role.split(":")[0]
            self._pubs[role] = self.node.publisher(self.topics[role], TYPES[kind], QOS[kind], priority=PRIORITY[kind],
                                                   blocking=kind in QUEUED)
        return self._pubs[role]

    def soon(self, role: str, build, kind: str | None = None) -> None:
        """Queue `build()` -> message for topic `role` on the per-frame thread (every one is sent, in order)."""
        self.publisher(role, kind)
        self._fast.put(role, build, keep_all=True)

    def later(self, role: str, build, *, kind: str | None = None, keep_all: bool = False) -> None:
        """Queue `build()` -> message for topic `role`; only the newest waiting one goes unless `keep_all`."""
        self.publisher(role, kind)  # announced now, so subscribers can match before the first message
        self._slow.put(role, build, keep_all)

    @contextlib.contextmanager
    def held(self):
        """Queue without waking the threads until the block ends: they take the interpreter (GIL) from the caller
        only once the caller's publishing is done."""
        self._fast.held = self._slow.held = True
        try:
            yield self
        finally:
            self._fast.release()
            self._slow.release()

    def path(self, stamps: np.ndarray, T_world_cam: np.ndarray, role: str = "path") -> None:
        """A trajectory as nav_msgs/Path on `role` (queued; copies are taken now)."""
        stamps, T = np.array(stamps, float), np.array(T_world_cam, float)
        self.later(role, lambda: M.path(self.ty, stamps, T, self.frame), kind="path")

    def cloud(self, role: str, t: float, arrays) -> None:
        """A point cloud on `role` ("submap": every one is sent; others: the newest); `arrays()` -> (xyz [N, 3],
        rgb [N, 3] uint8) is called on the worker thread."""
        def build():
            xyz, rgb = arrays()
            return M.point_cloud(self.ty, t, xyz, rgb, self.frame)

        self.later(role, build, kind="map", keep_all=role == "submap")

    def loops(self, t: float, loops: list) -> None:
        """Accepted loop edges [(p_i, p_j, "intra" | "inter")] as markers (queued)."""
        loops = [(np.array(a, float), np.array(b, float), k) for a, b, k in loops]
        self.later("loops", lambda: M.loop_markers(self.ty, M.header(self.ty, t, self.frame), loops))

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until everything queued has gone (True) or `timeout` s passed (False)."""
        t_end = time.monotonic() + timeout
        return self._fast.flush(timeout) and self._slow.flush(max(0.0, t_end - time.monotonic()))

    def stats(self) -> dict:
        return {"sent": dict(self.sent), "superseded": dict(self._fast.superseded + self._slow.superseded),
                "failed": self._fast.failed + self._slow.failed,
                "topics": {r: t for r, t in self.topics.items() if r in self._pubs}}

    def close(self, timeout: float = 10.0) -> None:
        """Send what waits (up to `timeout` s), then stop the threads and undeclare the publishers."""
        self.flush(timeout)
        self._fast.close()
        self._slow.close()
        for p in self._pubs.values():
            p.close()
        self._pubs = {}


class AgentTopics(Topics):
    """An agent's topics (see the module docstring); `base` is the topics' namespace, `topics` overrides any."""

    def __init__(self, node, agent: str, *, base: str = "/swarmsplat", topics: dict[str, str] | None = None,
                 frame: str = "map"):
        name = ros_token(agent)
        default = {r: f"{base.rstrip('/')}/{name}/{r}" for r in ("pose", "path", "submap", "map", "loops")}
        super().__init__(node, {**default, "tf": "/tf", **(topics or {})}, frame=frame)
        self.child_frame = f"{name}/camera"
        self.pose_sent_at: list[float] = []  # time.monotonic() at which each pose was sent
        for role in self.topics:  # all announced now: the ROS graph shows them before their first message
            self.publisher(role)

    def _send(self, role: str, msg) -> None:
        super()._send(role, msg)
        if role == "pose":
            self.pose_sent_at.append(time.monotonic())

    @property
    def published(self) -> int:
        """Poses sent (as PosePublisher counts them)."""
        return self.sent["pose"]

    def pose(self, t: float, T_world_cam: np.ndarray) -> None:
        """The frame's pose and its TF map -> <agent>/camera (queued for the per-frame thread)."""
        T = np.array(T_world_cam, float)
        self.soon("pose", lambda: M.pose_stamped(self.ty, t, T, self.frame))
        self.soon("tf", lambda: M.tf(self.ty, t, [(T, self.frame, self.child_frame)]))


class TeamTopics(Topics):
    """The team server's topics: every agent's corrected trajectory, the merged map, the loops."""

    def __init__(self, node, *, base: str = "/swarmsplat/team", frame: str = "map"):
        self.base = base.rstrip("/")
        super().__init__(node, {"map": f"{self.base}/map", "loops": f"{self.base}/loops"}, frame=frame)
        for role in ("map", "loops"):
            self.publisher(role)

    def trajectories(self, paths: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """{agent: (stamps [N], T_world_cam [N, 4, 4])} in the team's frame, each on <base>/<agent>/path
        (queued)."""
        for a, (stamps, T) in paths.items():
            self.topics.setdefault(f"path:{a}", f"{self.base}/{ros_token(a)}/path")
            self.path(stamps, T, role=f"path:{a}")

    def map(self, t: float, arrays) -> None:
        """The merged map (`arrays()` -> (xyz, rgb), called on the worker thread; the newest waiting one goes)."""
        self.cloud("map", t, arrays)

