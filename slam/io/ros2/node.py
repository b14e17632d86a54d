"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: a liveliness token for the node and one for each of its
publishers and subscriptions (what `ros2 node list` / `ros2 topic list` read), data on rmw_zenoh's keys with the
attachment on every sample. In the bridge form (`form="bridge"`, zenoh-bridge-ros2dds' convention) a publisher
puts plain keys and nothing is announced.

    node = Ros2Node(session, "agent_a", namespace="/swarmsplat", domain=0)
    pub = node.publisher("/swarmsplat/a/pose", "geometry_msgs/msg/PoseStamped", Qos(reliable=False))
    pub.put(msg)               # a message of slam.io.ros2.types.store()
    node.close()
"""

from __future__ import annotations

import hashlib
import itertools
import os
import re
import threading
import time

from swarmsplat.kernels.errors import InputError

from . import keys
from .keys import Qos
from .types import serialize, type_hash


def domain_id(value: int | None = None) -> int:
    """The ROS domain: `value`, else ROS_DOMAIN_ID, else 0 (0 .. 232, as ROS 2 allows)."""
    if value is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
        try:
            value = int(text)
        except ValueError:
            raise InputError(f"ROS_DOMAIN_ID={text!r}: expected an integer 0 .. 232") from None
    if not 0 <= int(value) <= 232:
        raise InputError(f"ROS domain id {value}: expected 0 .. 232")
    return int(value)


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def check_name(kind: str, name: str) -> str:
    """A ROS node name (one token) or a namespace / topic (tokens separated by slashes): letters, digits and
    underscores, not starting with a digit."""
    parts = [name] if kind == "node name" else name.strip("/").split("/")
    if not all(_NAME.fullmatch(p) for p in parts):
        raise InputError(f"{kind} {name!r}: expected letters, digits and underscores, not starting with a digit"
                         + ("" if kind == "node name" else ", separated by /"))
    return name


def _cached_publisher(session, key: str, depth: int, options: dict):
    """A Zenoh advanced publisher keeping its last `depth` samples for late subscribers (what rmw_zenoh declares
    for transient-local durability), or None when the session cannot (it needs timestamping, which
    slam.io.live.zenoh_config enables)."""
    import zenoh
    import zenoh.ext

    try:
        return zenoh.ext.declare_advanced_publisher(session, key, cache=zenoh.ext.CacheConfig(max_samples=depth),
                                                    publisher_detection=True, **options)
    except zenoh.ZError:
        return None


class Ros2Publisher:
    """One topic's publisher. `put(msg)` serialises and sends; `put_bytes(cdr)` sends CDR bytes as they are.
    `priority` is Zenoh's (a name of zenoh.Priority: a link sends higher priorities first, so small pose messages
    do not queue behind a large cloud); `blocking` waits for a congested link instead of dropping."""

    def __init__(self, node: Ros2Node, topic: str, msgtype: str, qos: Qos, entity_id: int, *,
                 priority: str = "DATA", blocking: bool = False):
        import zenoh

        self.topic, self.msgtype = topic, msgtype
        self.type_hash = type_hash(msgtype)
        self.sequence = 0
        self._lock = threading.Lock()
        s = node.session
        self.key = keys.topic_key(node.domain, topic, msgtype, self.type_hash) if node.form == "rmw" \
            else keys.bridge_key(topic, node.prefix)
        # DROP: a slow subscriber never blocks the caller (rmw_zenoh does the same for keep-last history); BLOCK for
        # a publisher that is used from a thread of its own, where waiting costs no one
        options = dict(congestion_control=zenoh.CongestionControl.BLOCK if blocking else zenoh.CongestionControl.DROP,
                       reliability=zenoh.Reliability.RELIABLE if qos.reliable else zenoh.Reliability.BEST_EFFORT,
                       priority=getattr(zenoh.Priority, priority))
        self._pub, self.qos = None, qos
        if qos.transient_local and node.form == "rmw":  # as rmw_zenoh: the last `depth` samples cached for late
            self._pub = _cached_publisher(s, self.key, qos.depth, options)  # subscribers to query
            if self._pub is None:
                self.qos = Qos(reliable=qos.reliable, transient_local=False, depth=qos.depth)
        if self._pub is None:
            self._pub = s.declare_publisher(self.key, **options)
        if node.form == "rmw":
            token = keys.endpoint_token(node.domain, node.zid, node.node_id, entity_id, "MP", node.namespace,
                                        node.name, topic, msgtype, self.type_hash, self.qos)
            self.gid = hashlib.sha256(token.encode()).digest()[:16]
            self._token = s.liveliness().declare_token(token)
        else:
            self.gid, self._token = b"", None

    def put(self, msg) -> None:
        self.put_bytes(serialize(msg))

    def put_bytes(self, cdr: bytes) -> None:
        with self._lock:
            self.sequence += 1
            if self.gid:
                self._pub.put(cdr, attachment=keys.attachment(self.sequence, time.time_ns(), self.gid))
            else:
                self._pub.put(cdr)

    def close(self) -> None:
        if self._pub is not None:
            self._pub.undeclare()
        if self._token is not None:
            self._token.undeclare()
        self._pub = self._token = None


class Ros2Node:
    """A node named `name` in `namespace` on a Zenoh session, in rmw_zenoh's form (default) or the bridge's."""

    _ids = itertools.count()

    def __init__(self, session, name: str, *, namespace: str = "/", domain: int | None = None, form: str = "rmw",
                 prefix: str = ""):
        if form not in keys.FORMS:
            raise InputError(f"ROS 2 key form {form!r}: expected one of {', '.join(keys.FORMS)}")
        self.session, self.form, self.prefix = session, form, prefix
        self.name = check_name("node name", name)
        self.namespace = "/" + check_name("namespace", namespace).strip("/") if namespace.strip("/") else "/"
        self.domain = domain_id(domain)
        self.zid = str(session.info.zid())
        self.node_id = next(Ros2Node._ids)
        self._entities = itertools.count(self.node_id * 1000 + 1)
        self._tokens = []
        self.publishers: list[Ros2Publisher] = []
        if form == "rmw":
            self._tokens.append(session.liveliness().declare_token(
                keys.node_token(self.domain, self.zid, self.node_id, self.namespace, self.name)))

    def publisher(self, topic: str, msgtype: str, qos: Qos = Qos(), *, priority: str = "DATA",
                  blocking: bool = False) -> Ros2Publisher:
        if self.form == "rmw":  # a bridge key is any Zenoh key
            check_name("topic", topic)
        pub = Ros2Publisher(self, "/" + topic.strip("/"), msgtype, qos, next(self._entities), priority=priority,
                            blocking=blocking)
        self.publishers.append(pub)
        return pub

    def subscription_token(self, topic: str, msgtype: str, qos: Qos = Qos()) -> None:
        """Announce a subscription of this node (rmw form; the data subscription itself is the caller's)."""
        if self.form == "rmw":
            self._tokens.append(self.session.liveliness().declare_token(keys.endpoint_token(
                self.domain, self.zid, self.node_id, next(self._entities), "MS", self.namespace, self.name,
                "/" + topic.strip("/"), msgtype, type_hash(msgtype), qos)))

    def close(self) -> None:
        for p in self.publishers:
            p.close()
        for t in self._tokens:
            t.undeclare()
        self.publishers, self._tokens = [], []
