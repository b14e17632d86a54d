"""Which topics of a bag make a sequence: colour, depth, camera info, odometry and ground truth, given by the
user (`--topics color=/cam/color/image_raw,depth=...`) or found from the topics' types and names.

Found means the only plausible one: colour is an Image / CompressedImage topic without "depth" in its name (a
raw Image over its own `/compressed` republication), depth one with it (the colour-aligned one first), the camera
info the CameraInfo topic nearest the colour topic, odometry a nav_msgs/Odometry or PoseStamped topic, ground
truth one whose name says so. Several colour topics that differ only in their first namespace (`/robot1/...`,
`/robot2/...`) are a team, one agent per namespace; any other ambiguity is an error listing the candidates.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from swarmsplat.kernels.errors import InputError

from .decode import CAMERA_INFO, COMPRESSED, IMAGE, POSE_TYPES

ROLES = ("color", "depth", "info", "odometry", "gt")
_GT_WORDS = re.compile(r"(ground_?truth|(^|/)gt(/|$)|mocap|vicon|optitrack)", re.IGNORECASE)


@dataclass(frozen=True)
class TopicChoice:
    color: str
    depth: str | None = None
    info: str | None = None
    odometry: str | None = None
    gt: str | None = None

    def as_dict(self) -> dict[str, str]:
        return {r: getattr(self, r) for r in ROLES if getattr(self, r)}


def parse_topics(text: str | None) -> dict[str, str]:
    """`color=/a,depth=/b` -> {"color": "/a", "depth": "/b"} (roles: color, depth, info, odometry, gt)."""
    if not text:
        return {}
    out: dict[str, str] = {}
    for part in text.split(","):
        role, sep, topic = part.strip().partition("=")
        role = role.strip().lower()
        if not sep or role not in ROLES or not topic.strip():
            raise InputError(f"--topics: expected ROLE=TOPIC[,ROLE=TOPIC...] with ROLE one of {', '.join(ROLES)}, "
                             f"got {part.strip()!r}")
        out[role] = topic.strip()
    return out


def _namespace(topic: str) -> str:
    parts = topic.strip("/").split("/")
    return "/" + parts[0] if len(parts) > 1 else ""


def _common_prefix(a: str, b: str) -> int:
    pa, pb = a.strip("/").split("/"), b.strip("/").split("/")
    n = 0
    while n < min(len(pa), len(pb)) and pa[n] == pb[n]:
        n += 1
    return n


def _images(types: dict[str, str], depth: bool) -> list[str]:
    found = [t for t, ty in types.items() if ty in IMAGE + COMPRESSED and ("depth" in t.lower()) == depth]
    raw = {t for t in found if types[t] in IMAGE}
    # image_transport republishes a raw topic as <topic>/compressed (colour) or <topic>/compressedDepth: one stream
    return sorted(t for t in found if not (types[t] in COMPRESSED and t.rsplit("/", 1)[0] in raw))


def _pick(cands: list[str], role: str, bag: str, types: dict[str, str], prefer=None, near: str | None = None
          ) -> str | None:
    """The one candidate, after keeping those `prefer` likes and those sharing most of `near`'s namespaces."""
    if prefer is not None and len(cands) > 1:
        best = [c for c in cands if prefer(c)]
        cands = best or cands
    if near is not None and len(cands) > 1:
        most = max(_common_prefix(near, c) for c in cands)
        cands = [c for c in cands if _common_prefix(near, c) == most]
    if len(cands) > 1:
        listed = ", ".join(f"{c} ({types[c]})" for c in cands)
        raise InputError(f"{bag}: several {role} topics could be meant: {listed}; choose with --topics "
                         f"{role}=TOPIC")
    return cands[0] if cands else None


def choose_topics(types: dict[str, str], given: dict[str, str] | None, bag: str, *,
                  namespace: str = "") -> TopicChoice:
    """The topics of one agent. `types` maps every topic of the bag to its message type; `given` wins where set;
    `namespace` restricts the search to one agent's topics ("/robot1")."""
    given = dict(given or {})
    for role, topic in given.items():
        if topic not in types:
            raise InputError(f"{bag}: topic {topic!r} (--topics {role}=) is not in the bag; it has "
                             f"{', '.join(sorted(types)) or 'no topics'}")
    pool = {t: ty for t, ty in types.items() if not namespace or t.startswith(namespace + "/")}
    color = given.get("color") or _pick(_images(pool, depth=False), "color", bag, pool,
                                        prefer=lambda t: bool(re.search(r"colou?r|rgb", t, re.IGNORECASE)))
    if color is None:
        raise InputError(f"{bag}: no colour image topic (sensor_msgs/Image or CompressedImage) found; topics: "
                         f"{', '.join(f'{t} ({ty})' for t, ty in sorted(types.items())) or 'none'}")
    depth = given.get("depth") or _pick(_images(pool, depth=True), "depth", bag, pool, near=color,
                                        prefer=lambda t: "align" in t.lower() or "regist" in t.lower())
    infos = [t for t, ty in pool.items() if ty in CAMERA_INFO and "depth" not in t.lower()] or \
        [t for t, ty in pool.items() if ty in CAMERA_INFO]
    info = given.get("info") or _pick(sorted(infos), "info", bag, pool, near=color)
    poses = sorted(t for t, ty in pool.items() if ty in POSE_TYPES)
    gt = given.get("gt") or _pick([t for t in poses if _GT_WORDS.search(t)], "gt", bag, pool, near=color)
    odom = given.get("odometry") or _pick([t for t in poses if not _GT_WORDS.search(t) and t != gt], "odometry",
                                          bag, pool, prefer=lambda t: "odom" in t.lower(), near=color)
    return TopicChoice(color=color, depth=depth, info=info, odometry=odom, gt=gt)


def agent_namespaces(types: dict[str, str], given: dict[str, str] | None) -> list[str]:
    """[""] for one agent; ["/robot1", "/robot2", ...] when the colour topics differ only in their first
    namespace (and none was given)."""
    if given and given.get("color"):
        return [""]
    colors = _images(types, depth=False)
    if len(colors) < 2:
        return [""]
    spaces = [_namespace(t) for t in colors]
    rests = {t[len(ns):] for t, ns in zip(colors, spaces)}
    if all(spaces) and len(set(spaces)) == len(colors) and len(rests) == 1:
        return sorted(spaces)
    return [""]  # choose_topics then names the ambiguity

