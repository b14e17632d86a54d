"""How ROS 2 names things on Zenoh, the two ways there are.

rmw_zenoh (ROS 2's Zenoh middleware):
  data         `<domain>/<topic without its leading slash>/<DDS type>/<RIHS01 hash>`, e.g.
               `0/swarmsplat/a/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3...`
  liveliness   `@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>` for a
               node (kind NN), followed by `/<topic>/<DDS type>/<hash>/<QoS>` for a publisher (MP) or a
               subscription (MS); names inside a token have their slashes written as `%` (an empty namespace is
               `%`), so one name is one key chunk.
  attachment   on every sample: sequence number (int64), source timestamp (int64, ns since the epoch) and the
               publisher's GID (16 bytes), little-endian, the GID after its length as one byte (33 bytes).
zenoh-bridge-ros2dds: data on `[PREFIX/]<topic without its leading slash>`, no liveliness, no attachment.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .types import dds_name, ros_name

LIVELINESS = "@ros2_lv"
FORMS = ("rmw", "bridge")


@dataclass(frozen=True)
class Qos:
    """A ROS 2 QoS profile as rmw_zenoh encodes it in liveliness tokens (reliable, volatile, keep last 10 is ROS 2's
    default profile)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def text(self) -> str:
        """`<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>`, defaults left empty
        (RMW's enums: best effort 2, transient local 1)."""
        return (f"{'' if self.reliable else 2}:{1 if self.transient_local else ''}:,{self.depth}"
                f":,:,:,,")

    def describe(self) -> str:
        return (f"{'reliable' if self.reliable else 'best effort'}, "
                f"{'transient local' if self.transient_local else 'volatile'}, keep last {self.depth}")


def mangle(name: str) -> str:
    """A ROS name as one key chunk: slashes become `%` ('' and '/' become '%')."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def topic_key(domain: int, topic: str, msgtype: str, type_hash: str) -> str:
    """rmw_zenoh's data key of `topic` (an absolute ROS name) carrying `msgtype`."""
    return f"{int(domain)}/{topic.strip('/')}/{dds_name(msgtype)}/{type_hash}"


def bridge_key(topic: str, prefix: str = "") -> str:
    """zenoh-bridge-ros2dds' key of `topic`: the topic without its leading slash, after `prefix`."""
    return "/".join(p for p in (prefix.strip("/"), topic.strip("/")) if p)


def parse_topic_key(key: str) -> tuple[int, str, str, str] | None:
    """(domain, topic, ROS type, type hash) of an rmw_zenoh data key, or None if `key` is not one."""
    parts = key.strip("/").split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        return None
    msgtype = ros_name(parts[-2])
    if msgtype is None:
        return None
    return int(parts[0]), "/" + "/".join(parts[1:-2]), msgtype, parts[-1]


def node_token(domain: int, zid: str, node_id: int, namespace: str, name: str, enclave: str = "") -> str:
    """The liveliness key that announces a node."""
    return f"{LIVELINESS}/{int(domain)}/{zid}/{node_id}/{node_id}/NN/{mangle(enclave)}/{mangle(namespace)}/{name}"


def endpoint_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, name: str,
                   topic: str, msgtype: str, type_hash: str, qos: Qos, enclave: str = "") -> str:
    """The liveliness key that announces a publisher (kind MP) or a subscription (MS) of a node."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"endpoint kind {kind!r}: expected MP or MS")
    return (f"{LIVELINESS}/{int(domain)}/{zid}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/{mangle(namespace)}/"
            f"{name}/{mangle(topic)}/{dds_name(msgtype)}/{type_hash}/{qos.text()}")


def attachment(sequence: int, stamp_ns: int, gid: bytes) -> bytes:
    """The attachment rmw_zenoh puts on a sample (33 bytes for a 16-byte GID)."""
    if len(gid) != 16:
        raise ValueError(f"a publisher GID has 16 bytes, got {len(gid)}")
    return struct.pack("<qqB", int(sequence), int(stamp_ns), 16) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment."""
    if len(data) < 17 or len(data) != 17 + data[16]:
        raise ValueError(f"an rmw_zenoh attachment has 17 + GID-length bytes, got {len(data)}")
    seq, stamp = struct.unpack_from("<qq", data)
    return seq, stamp, bytes(data[17:])
