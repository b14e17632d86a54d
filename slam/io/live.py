"""Live ROS 2 topics over Zenoh, no ROS install: RGB-D frames in, tracked poses out.

ROS 2 reaches Zenoh two ways, and both are read: the Zenoh-ROS 2 bridge (`zenoh-bridge-ros2dds`) puts topic
`/camera/color/image_raw` on key `[PREFIX/]camera/color/image_raw`; `rmw_zenoh` on
`<domain>/camera/color/image_raw/<type>/<hash>`. Payloads are CDR (with their 4-byte encapsulation header), as in
a ROS 2 bag, and are decoded with `rosbags`. `ZenohRos2Source` subscribes to `PREFIX/**` once and routes a sample
to the colour, depth or camera-info role whose topic its key holds; a reader thread decodes and pairs colour and
depth by header stamp (within `max_diff`), so Zenoh's own thread only queues bytes and no sample is dropped while
the pipeline is busy (up to `max_queue` frames, then the oldest go and are counted). `PosePublisher` puts
`geometry_msgs/PoseStamped` (and a `nav_msgs/Path` of the keyframes after each pose-graph optimisation) as CDR.
"""

from __future__ import annotations

import collections
import queue
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.se3 import matrix_to_quat_wxyz

from .bags.decode import camera_from_info, decode_color, decode_depth, stamp_of
from .datasets.base import Frame

DEFAULT_TOPICS = {"color": "/camera/color/image_raw", "depth": "/camera/depth/image_raw",
                  "info": "/camera/color/camera_info"}
_TYPES = {"Image": "sensor_msgs/msg/Image", "CompressedImage": "sensor_msgs/msg/CompressedImage",
          "CameraInfo": "sensor_msgs/msg/CameraInfo"}


def zenoh_config(*, connect: list[str] = (), listen: list[str] = (), multicast: bool = False):
    """A peer-mode Zenoh config: listen / connect endpoints (`tcp/host:port`), multicast scouting off by default
    (explicit endpoints keep a run on the machines it names)."""
    try:
        import zenoh
    except ImportError:
        raise InputError("live ROS 2 input needs eclipse-zenoh: pip install eclipse-zenoh") from None
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast else "false")
    for key, eps in (("listen/endpoints", listen), ("connect/endpoints", connect)):
        if eps:
            conf.insert_json5(key, "[" + ",".join(f'"{e}"' for e in eps) + "]")
    return zenoh, conf


def role_of_key(key: str, topics: dict[str, str]) -> str | None:
    """The role whose ROS topic the Zenoh key carries (bridge: `PREFIX/<topic>`; rmw_zenoh:
    `<domain>/<topic>/<type>/<hash>`), longest topic first."""
    padded = "/" + key.strip("/") + "/"
    for role, topic in sorted(topics.items(), key=lambda kv: -len(kv[1])):
        t = "/" + topic.strip("/") + "/"
        if padded.endswith(t):
            return role
        at = padded.find(t)
        if at >= 0 and "::" in padded[at + len(t):].split("/", 1)[0]:  # rmw_zenoh: the type follows the topic
            return role
    return None


def _msgtype(role: str, topic: str, key: str) -> str:
    if "CompressedImage" in key or topic.rstrip("/").endswith(("/compressed", "/compressedDepth")):
        return _TYPES["CompressedImage"]
    return _TYPES["CameraInfo"] if role == "info" else _TYPES["Image"]


@dataclass
class SourceStats:
    samples: dict = field(default_factory=lambda: collections.Counter())  # per role
    frames: int = 0  # colour + depth pairs handed out
    unpaired: int = 0  # colour or depth with no partner within max_diff
    dropped: int = 0  # paired frames pushed out of a full queue
    undecodable: int = 0


class ZenohRos2Source:
    """RGB-D frames from live ROS 2 topics over Zenoh. `frames(...)` yields (Frame, arrival, taken) as they pair up:
    arrival is the time.monotonic() at which the later of the two messages arrived, taken when the frame left the
    queue (before decoding); `camera` is known once a camera_info arrived."""

    def __init__(self, prefix: str = "", topics: dict[str, str] | None = None, *, name: str = "live",
                 connect: list[str] = (), listen: list[str] = (), max_diff: float = 0.02, max_queue: int = 300,
                 session=None):
        self.prefix = prefix.strip("/")
        self.topics = {**DEFAULT_TOPICS, **(topics or {})}
        unknown = set(self.topics) - set(DEFAULT_TOPICS)
        if unknown:
            raise InputError(f"live topics: roles {sorted(unknown)} are not read live; expected color, depth, info")
        self.name, self.max_diff, self.max_queue = name, float(max_diff), int(max_queue)
        self.camera: PinholeCamera | None = None
        self.stats = SourceStats()
        self._raw: queue.SimpleQueue = queue.SimpleQueue()
        self._frames: collections.deque = collections.deque()
        self._ready = threading.Condition()
        self._store = None
        self._stop = threading.Event()
        self._last_sample = time.monotonic()
        self._own_session = session is None
        if session is None:
            zenoh, conf = zenoh_config(connect=list(connect), listen=list(listen))
            session = zenoh.open(conf)
        self.session = session
        key = f"{self.prefix}/**" if self.prefix else "**"
        self._sub = session.declare_subscriber(key, self._on_sample)
        self._thread = threading.Thread(target=self._decode_loop, name="live-decode", daemon=True)
        self._thread.start()

    # ---- Zenoh's thread: route and queue, nothing else ------------------------------------------------------

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        role = role_of_key(key[len(self.prefix):] if key.startswith(self.prefix) else key, self.topics)
        if role is not None:
            self._raw.put((role, key, sample.payload.to_bytes(), time.monotonic()))

    # ---- the reader thread: decode, pair ----------------------------------------------------------------------

    def _decode_loop(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self._store = get_typestore(Stores.ROS2_HUMBLE)
        pending = {"color": collections.deque(maxlen=64), "depth": collections.deque(maxlen=64)}
        while not self._stop.is_set():
            try:
                role, key, data, arrival = self._raw.get(timeout=0.1)
            except queue.Empty:
                continue
            self._last_sample = time.monotonic()
            self.stats.samples[role] += 1
            topic = self.topics[role]
            mtype = _msgtype(role, topic, key)
            try:
                msg = self._store.deserialize_cdr(data, mtype)
            except Exception:  # noqa: BLE001 - a sample of another type on a matching key, or garbage
                self.stats.undecodable += 1
                continue
            if role == "info":
                if self.camera is None:
                    self.camera = camera_from_info(msg, f"zenoh {key}")[0]
                    with self._ready:
                        self._ready.notify_all()
                continue
            pending[role].append((stamp_of(msg), msg, mtype, key, arrival))
            self._pair(pending)

    def _pair(self, pending) -> None:
        while pending["color"] and pending["depth"]:
            c, d = pending["color"][0], pending["depth"][0]
            if abs(c[0] - d[0]) <= self.max_diff:
                pending["color"].popleft()
                pending["depth"].popleft()
                self._push(c, d)
            elif c[0] < d[0]:
                pending["color"].popleft()
                self.stats.unpaired += 1
            else:
                pending["depth"].popleft()
                self.stats.unpaired += 1

    def _push(self, c, d) -> None:
        with self._ready:
            if len(self._frames) >= self.max_queue:
                self._frames.popleft()
                self.stats.dropped += 1
            self._frames.append((c, d))
            self._ready.notify_all()

    # ---- the consumer -----------------------------------------------------------------------------------------

    def wait_camera(self, timeout: float) -> PinholeCamera:
        with self._ready:
            self._ready.wait_for(lambda: self.camera is not None, timeout=timeout)
        if self.camera is None:
            raise InputError(f"live source: no camera_info on {self.topics['info']} within {timeout:g} s "
                             f"(Zenoh key prefix {self.prefix or '(none)'}); check --topics info= and --connect")
        return self.camera

    def frames(self, *, max_frames: int = 0, idle_timeout: float = 0.0, silent_warning: float = 5.0,
               stop=None):
        """Frames in arrival order until `max_frames` (0: no limit), `idle_timeout` seconds without a sample (0: wait
        for ever), `stop()` returns true (checked at least every 0.2 s) or `close()`. A warning every
        `silent_warning` seconds without a sample."""
        n, warned_at = 0, 0.0
        while not self._stop.is_set() and (not max_frames or n < max_frames) and not (stop and stop()):
            with self._ready:
                self._ready.wait_for(lambda: self._frames or self._stop.is_set(), timeout=0.2)
                item = self._frames.popleft() if self._frames else None
            taken = time.monotonic()
            if item is None:
                silent = time.monotonic() - self._last_sample
                if idle_timeout and silent >= idle_timeout:
                    return
                if silent_warning and silent >= silent_warning and silent - warned_at >= silent_warning:
                    warned_at = silent
                    warnings.warn(f"live source: no sample for {silent:.0f} s on {self._topics_text()}", stacklevel=2)
                continue
            warned_at = 0.0
            frame = self._frame(n, *item)
            if frame is not None:
                n += 1
                yield frame, max(item[0][4], item[1][4]), taken

    def _frame(self, index: int, c, d) -> Frame | None:
        (t, cmsg, ctype, ckey, _), (_, dmsg, dtype, dkey, _) = c, d
        try:
            color = decode_color(cmsg, ctype, f"zenoh {ckey}")
            depth = decode_depth(dmsg, dtype, f"zenoh {dkey}")
        except InputError as e:
            self.stats.undecodable += 1
            warnings.warn(str(e), stacklevel=3)
            return None
        self.stats.frames += 1
        return Frame(index=index, timestamp=t, color=color, depth=depth)

    def _topics_text(self) -> str:
        return ", ".join(f"{r} {t}" for r, t in self.topics.items())

    def close(self) -> None:
        self._stop.set()
        with self._ready:
            self._ready.notify_all()
        self._thread.join(timeout=2.0)
        self._sub.undeclare()
        if self._own_session:
            self.session.close()


class PosePublisher:
    """Puts a frame's pose as geometry_msgs/PoseStamped on `key`, and the keyframe trajectory as nav_msgs/Path on
    `key/path`, CDR-encoded (what a ROS 2 node behind the bridge or rmw_zenoh receives)."""

    def __init__(self, session, key: str, frame_id: str = "map"):
        from rosbags.typesys import Stores, get_typestore

        self.session, self.key, self.frame_id = session, key.strip("/"), frame_id
        self.store = get_typestore(Stores.ROS2_HUMBLE)
        self.published = 0

    def _pose_stamped(self, t: float, T: np.ndarray):
        ty = self.store.types
        sec = int(np.floor(t))
        stamp = ty["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)
        q = matrix_to_quat_wxyz(T[:3, :3])
        pose = ty["geometry_msgs/msg/Pose"](
            position=ty["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            orientation=ty["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))
        header = ty["std_msgs/msg/Header"](stamp=stamp, frame_id=self.frame_id)
        return ty["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)

    def pose(self, t: float, T_world_cam: np.ndarray) -> None:
        msg = self._pose_stamped(t, T_world_cam)
        self.session.put(self.key, bytes(self.store.serialize_cdr(msg, msg.__msgtype__)))
        self.published += 1

    def path(self, stamps: np.ndarray, T_world_cam: np.ndarray) -> None:
        poses = [self._pose_stamped(float(t), T) for t, T in zip(stamps, T_world_cam)]
        header = poses[-1].header if poses else self._pose_stamped(0.0, np.eye(4)).header
        msg = self.store.types["nav_msgs/msg/Path"](header=header, poses=poses)
        self.session.put(self.key + "/path", bytes(self.store.serialize_cdr(msg, msg.__msgtype__)))
