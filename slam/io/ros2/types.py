"""The ROS 2 message types swarmsplat speaks, from the definitions shipped beside this module (msg/<package>/
<Name>.msg: ROS 2 Jazzy's sensor_msgs, geometry_msgs, nav_msgs, std_msgs, visualization_msgs, tf2_msgs and
builtin_interfaces, Apache-2.0), with their DDS names and RIHS01 type hashes (REP 2011: SHA-256 of the type
description, what rmw_zenoh puts in its keys). Nothing is fetched: the store is built from these files once.
"""

from __future__ import annotations

import functools
from pathlib import Path

MSG_DIR = Path(__file__).resolve().parent / "msg"


@functools.lru_cache(maxsize=1)
def store():
    """A rosbags typestore holding exactly the shipped definitions (CDR serialisation, RIHS01 hashes)."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    ts = get_typestore(Stores.EMPTY)
    types: dict = {}
    for path in sorted(MSG_DIR.glob("*/*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"{path.parent.name}/msg/{path.stem}"))
    ts.register(types)
    return ts


@functools.lru_cache(maxsize=None)
def type_hash(msgtype: str) -> str:
    """`RIHS01_<64 hex>` of a type, e.g. type_hash("geometry_msgs/msg/PoseStamped")."""
    return store().hash_rihs01(msgtype)


def dds_name(msgtype: str) -> str:
    """The DDS type name rmw_zenoh writes in keys: sensor_msgs/msg/Image -> sensor_msgs::msg::dds_::Image_."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_name(dds: str) -> str | None:
    """The ROS type of a DDS type name (the inverse of dds_name), or None if `dds` is not one."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def serialize(msg) -> bytes:
    """CDR bytes (with the encapsulation header) of a message of the store."""
    return bytes(store().serialize_cdr(msg, msg.__msgtype__))
