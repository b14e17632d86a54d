"""Live ROS 2 topics over Zenoh, no ROS install: RGB-D frames in, tracked poses out.

ROS 2 reaches Zenoh two ways, and both are read: the Zenoh-ROS 2 bridge (`zenoh-bridge-ros2dds`) puts topic
`/camera/color/image_raw` on key `[PREFIX/]camera/color/image_raw`; `rmw_zenoh` on
`<domain>/camera/color/image_raw/<type>/<hash>`. Payloads are CDR (with their 4-byte encapsulation header), as in
a ROS 2 bag, and are decoded with `rosbags`. `ZenohRos2Source` subscribes to `PREFIX/**` once and routes a sample
to the colour, depth or camera-info role whose topic its key holds; a reader thread decodes and pairs colour and
depth by header stamp (within `max_diff`), so Zenoh's own thread only queues bytes and no sample is dropped while
the pipeline is busy (up to `max_queue` frames, then the oldest go and are counted). What the agent publishes goes
out through slam.io.ros2 (rmw_zenoh's keys by default); `PosePublisher` is its plain-key form on one given key.
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

from .bags.decode import camera_from_info, decode_color, decode_depth, stamp_of
from .datasets.base import Frame
from .ros2 import AgentTopics, Ros2Node, parse_topic_key, type_hash

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
    conf.insert_json5("timestamping/enabled", "true")  # transient-local ROS 2 publishers (a cache) need it
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


def refuse_type(role: str, topic: str, key: str) -> str | None:
    """Why a sample on an rmw_zenoh key cannot be read for `role` (its type is not one read there, or its type hash
    is not the one of the shipped definitions), in one line naming the topic and what was expected; None if it can
    (and for a bridge key, which carries no type)."""
    parsed = parse_topic_key(key)
    if parsed is None:
        return None
    _, _, msgtype, got = parsed
    allowed = [_TYPES["CameraInfo"]] if role == "info" else [_TYPES["Image"], _TYPES["CompressedImage"]]
    if msgtype not in allowed:
        return f"{topic}: samples of {msgtype}; expected {' or '.join(allowed)}; ignored"
    want = type_hash(msgtype)
    if got not in (want, "TypeHashNotSupported"):  # rmw_zenoh on Humble has no type hashes
        return f"{topic}: type hash {got} of {msgtype}; expected {want} (ROS 2 Jazzy's definition); ignored"
    return None


@dataclass
class SourceStats:
    samples: dict = field(default_factory=lambda: collections.Counter())  # per role
    frames: int = 0  # colour + depth pairs handed out
    unpaired: int = 0  # colour or depth with no partner within max_diff
    dropped: int = 0  # paired frames pushed out of a full queue
    undecodable: int = 0


class ZenohRos2Source:
    """RGB-D frames from live ROS 2 topics over Zenoh (rmw_zenoh's keys of ROS domain `domain` only, when given;
    bridge keys always). `frames(...)` yields (Frame, arrival, taken) as they pair up:
    arrival is the time.monotonic() at which the later of the two messages arrived, taken when the frame left the
    queue (before decoding); `camera` is known once a camera_info arrived."""

    def __init__(self, prefix: str = "", topics: dict[str, str] | None = None, *, name: str = "live",
                 connect: list[str] = (), listen: list[str] = (), max_diff: float = 0.02, max_queue: int = 300,
                 session=None, domain: int | None = None):
        self.prefix = prefix.strip("/")
        self.domain = domain  # rmw_zenoh keys of another ROS domain are another graph: not read
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
        self._warned: set[str] = set()
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
        if role is not None and self.domain is not None and key.split("/", 1)[0] != str(self.domain) \
                and parse_topic_key(key) is not None:
            role = None
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
            refused = refuse_type(role, topic, key)
            if refused:
                self.stats.undecodable += 1
                self._warn_once(key, refused)
                continue
            try:
                msg = self._store.deserialize_cdr(data, mtype)
            except Exception:  # noqa: BLE001 - a sample of another type on a matching key, or garbage
                self.stats.undecodable += 1
                self._warn_once(key, f"{topic} (Zenoh key {key}): a sample that does not decode as {mtype}; "
                                     "ignored")
                continue
            if role == "info":
                if self.camera is None:
                    self.camera = camera_from_info(msg, f"{topic} (Zenoh key {key})")[0]
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
            color = decode_color(cmsg, ctype, f"{self.topics['color']} (Zenoh key {ckey})")
            depth = decode_depth(dmsg, dtype, f"{self.topics['depth']} (Zenoh key {dkey})")
            self._check_size(color, depth)
        except InputError as e:
            self.stats.undecodable += 1
            warnings.warn(str(e), stacklevel=3)
            return None
        self.stats.frames += 1
        return Frame(index=index, timestamp=t, color=color, depth=depth)

    def _check_size(self, color: np.ndarray, depth: np.ndarray) -> None:
        h, w = color.shape[:2]
        if depth.shape[:2] != (h, w):
            raise InputError(f"{self.topics['depth']}: depth of {depth.shape[1]}x{depth.shape[0]} beside colour of "
                             f"{w}x{h} on {self.topics['color']}; expected depth registered to the colour camera "
                             "(same size); frame skipped")
        cam = self.camera
        if cam is not None and (cam.width, cam.height) != (w, h):
            raise InputError(f"{self.topics['info']}: camera_info of {cam.width}x{cam.height} but images of {w}x{h} "
                             f"on {self.topics['color']}; expected the same size; frame skipped")

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            warnings.warn(text, stacklevel=2)

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


class PosePublisher(AgentTopics):
    """The bridge form with one key given (zenoh-bridge-ros2dds' convention, plain keys, no liveliness): poses on
    `key`, the keyframe path on `key/path`, clouds on `key/submap` and `key/map`, loops on `key/loops`, TF on
    `tf`. The default publications are rmw_zenoh's (slam.io.ros2.AgentTopics on an rmw-form node)."""

    def __init__(self, session, key: str, frame_id: str = "map"):
        key = key.strip("/")
        self.key = key
        super().__init__(Ros2Node(session, "swarmsplat", form="bridge"), "live", frame=frame_id,
                         topics={"pose": key, **{r: f"{key}/{r}" for r in ("path", "submap", "map", "loops")}})
