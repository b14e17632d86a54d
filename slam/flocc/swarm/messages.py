"""Versioned messages robots exchange, and their compact, safe binary form (no pickle).

Wire layout of every message (little endian):

    header  19 B   magic b"SWRM" | schema version u8 | type id u8 | sender robot id u8 | sequence u64 | payload u32
    payload        JSON length u32 | JSON object (scalar fields + array specs) | raw bytes of each array, in order

Arrays carry numbers only (descriptors, poses, encodings as bytes): their dtypes come from a short allow-list and
their shapes are checked against the message's schema, so decoding never runs code and never trusts a length it
has not checked. Anything else — a foreign magic, another schema version, an unknown type, a truncated or padded
buffer, a missing or mistyped field — raises `MessageError` (an `InputError`) and the receiver drops it.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

from swarmsplat.kernels.errors import InputError

MAGIC = b"SWRM"
SCHEMA_VERSION = 2  # 2: the end protocol (Finish); a robot without it would hold the others to the timeout
_HEADER = struct.Struct("<4sBBBQI")
HEADER_BYTES = _HEADER.size
MAX_PAYLOAD = 256 << 20  # 256 MiB: refuse absurd lengths before allocating anything
_DTYPES = {"<f2", "<f4", "<f8", "<i8", "|u1"}


class MessageError(InputError):
    """A buffer that is not a valid message of this schema version."""


@dataclass(frozen=True)
class Header:
    type_id: int
    sender: int  # robot id, 0..254
    seq: int  # per-sender sequence number


@dataclass
class Message:
    """Base of all messages. Subclasses list JSON scalar fields with Python types in `SCALARS` and array fields
    with (dtype, ndim) in `ARRAYS`; every dataclass field must appear in exactly one of them."""

    TYPE: ClassVar[int] = 0
    SCALARS: ClassVar[dict[str, type]] = {}
    ARRAYS: ClassVar[dict[str, tuple[str, int]]] = {}

    @property
    def kind(self) -> str:
        return type(self).__name__


def _check_poses(T: np.ndarray, what: str) -> None:
    """MessageError unless T [N, 4, 4] are finite rigid transforms (rotation orthonormal, det +1, last row 0001)."""
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise MessageError(f"{what}: poses must be finite [N, 4, 4]")
    if len(T):
        R = T[:, :3, :3]
        if np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-6 or np.any(np.linalg.det(R) < 0) \
                or np.abs(T[:, 3] - [0, 0, 0, 1]).max() > 0:
            raise MessageError(f"{what}: poses are not rigid transforms")


def _ints(xs) -> bool:
    return all(isinstance(x, int) and not isinstance(x, bool) for x in xs)


def _i64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.int64).reshape(-1)


@dataclass
class Hello(Message):
    """Heartbeat: what the sender has, so neighbours send only what it lacks.

    n_keyframes: the sender's own keyframes; have_desc: robot id (str) -> contiguous descriptor count held;
    loops_with: robot id (str) -> CRC of the inter-robot loop keys known between the sender and that robot;
    graph_version: [n_keyframes, loop digest] of the sender's own graph; graphs_held: robot id (str) -> the
    graph_version of that robot's submission the sender holds (meaningful when the sender is the optimiser);
    estimate_stamp: stamp of the sender's current global estimate ([] without one).
    """

    TYPE: ClassVar[int] = 1
    SCALARS: ClassVar[dict] = {"tick": int, "n_keyframes": int, "have_desc": dict, "loops_with": dict,
                               "graph_version": list, "graphs_held": dict, "estimate_stamp": list}
    tick: int = 0
    n_keyframes: int = 0
    have_desc: dict = field(default_factory=dict)
    loops_with: dict = field(default_factory=dict)
    graph_version: list = field(default_factory=list)
    graphs_held: dict = field(default_factory=dict)
    estimate_stamp: list = field(default_factory=list)

    def validate(self) -> None:
        ok = _ints(self.have_desc.values()) and _ints(self.loops_with.values()) and _ints(self.graph_version) \
            and _ints(self.estimate_stamp) and all(isinstance(v, list) and _ints(v) for v in self.graphs_held.values())
        keys = list(self.have_desc) + list(self.loops_with) + list(self.graphs_held)
        if not ok or not all(k.isdigit() and len(k) < 4 for k in keys):
            raise MessageError("Hello: maps must be robot id -> integer(s)")


@dataclass
class Descriptors(Message):
    """Global descriptors [N, D] float32 of keyframes `indices` [N] of robot `owner`."""

    TYPE: ClassVar[int] = 2
    SCALARS: ClassVar[dict] = {"owner": int}
    ARRAYS: ClassVar[dict] = {"indices": ("<i8", 1), "descriptors": ("<f4", 2)}
    owner: int = 0
    indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))

    def validate(self) -> None:
        if len(self.descriptors) != len(self.indices) or not np.all(np.isfinite(self.descriptors)) \
                or np.any(self.indices < 0):
            raise MessageError("Descriptors: one finite descriptor per non-negative keyframe index expected")


@dataclass
class EncodingRequest(Message):
    """Ask robot `owner` for the pair-registration encodings of its keyframes `indices` [N]."""

    TYPE: ClassVar[int] = 3
    SCALARS: ClassVar[dict] = {"owner": int}
    ARRAYS: ClassVar[dict] = {"indices": ("<i8", 1)}
    owner: int = 0
    indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


@dataclass
class EncodingReply(Message):
    """Encodings (`registration.pair.Encoding.to_bytes()`) of keyframes `indices` [N] of robot `owner`, packed
    in `blob` [B] uint8 with `offsets` [N + 1] (encoding n is blob[offsets[n]:offsets[n + 1]])."""

    TYPE: ClassVar[int] = 4
    SCALARS: ClassVar[dict] = {"owner": int, "camera": list}
    ARRAYS: ClassVar[dict] = {"indices": ("<i8", 1), "offsets": ("<i8", 1), "blob": ("|u1", 1)}
    owner: int = 0
    camera: list = field(default_factory=list)  # the owner's intrinsics [fx, fy, cx, cy, width, height]
    indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    blob: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))

    @classmethod
    def pack(cls, owner: int, camera: list, items: dict[int, bytes]) -> "EncodingReply":
        idx = sorted(items)
        sizes = [len(items[i]) for i in idx]
        blob = np.frombuffer(b"".join(items[i] for i in idx), np.uint8) if idx else np.zeros(0, np.uint8)
        return cls(owner=owner, camera=[float(c) for c in camera], indices=_i64(idx), offsets=_i64(np.concatenate([[0], np.cumsum(sizes)])), blob=blob)

    def items(self) -> dict[int, bytes]:
        return {int(i): self.blob[self.offsets[n]: self.offsets[n + 1]].tobytes() for n, i in enumerate(self.indices)}

    def validate(self) -> None:
        o = self.offsets
        if len(o) != len(self.indices) + 1 or (len(o) and (o[0] != 0 or o[-1] != len(self.blob))) \
                or np.any(np.diff(o) < 0):
            raise MessageError("EncodingReply: offsets do not partition the blob")
        if len(self.camera) != 6 or not all(isinstance(c, (int, float)) and np.isfinite(c) and c > 0 for c in self.camera):
            raise MessageError("EncodingReply: camera must be 6 positive numbers")


@dataclass
class LoopBatch(Message):
    """Inter-robot loop closures: keyframe `query_index` of `query_robot` sees keyframe `match_index` of
    `match_robot` at `T_query_match` [L, 4, 4] (unit translation), confidence p [L] (eq. 2), eq. 6 scale [L]."""

    TYPE: ClassVar[int] = 5
    SCALARS: ClassVar[dict] = {"version": list}
    ARRAYS: ClassVar[dict] = {"query_robot": ("<i8", 1), "query_index": ("<i8", 1), "match_robot": ("<i8", 1),
                              "match_index": ("<i8", 1), "T_query_match": ("<f8", 3), "confidence": ("<f8", 1),
                              "odom_scale": ("<f8", 1)}
    version: list = field(default_factory=list)  # the sender's knowledge when it made this set (newer: greater)
    query_robot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    query_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    match_robot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    match_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    T_query_match: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odom_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def validate(self) -> None:
        n = len(self.query_robot)
        if any(len(getattr(self, k)) != n for k in self.ARRAYS) or self.T_query_match.shape[1:] != (4, 4):
            raise MessageError("LoopBatch: arrays of different lengths")
        _check_poses(self.T_query_match, "LoopBatch")
        if np.any(self.query_index < 0) or np.any(self.match_index < 0) or np.any(self.query_robot < 0) \
                or np.any(self.match_robot < 0) or np.any(self.query_robot > 25) or np.any(self.match_robot > 25):
            raise MessageError("LoopBatch: robot ids must be in 0..25 and keyframe indices >= 0")
        if not (np.all(np.isfinite(self.T_query_match)) and np.all((self.confidence > 0) & (self.confidence <= 1))
                and np.all(np.isfinite(self.odom_scale)) and np.all(self.odom_scale > 0)):
            raise MessageError("LoopBatch: non-finite pose, confidence outside (0, 1] or non-positive scale")


@dataclass
class GraphSubmission(Message):
    """A robot's graph for the optimiser: its keyframe odometry poses T_odom_kf [N, 4, 4] and the loops it
    knows (a LoopBatch's arrays). `version` is [n_keyframes, loop digest]."""

    TYPE: ClassVar[int] = 6
    SCALARS: ClassVar[dict] = {"robot": int, "version": list}
    ARRAYS: ClassVar[dict] = {"odometry": ("<f8", 3), **LoopBatch.ARRAYS}
    robot: int = 0
    version: list = field(default_factory=list)
    odometry: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    query_robot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    query_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    match_robot: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    match_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    T_query_match: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odom_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def loops(self) -> LoopBatch:
        return LoopBatch(version=list(self.version), **{k: getattr(self, k) for k in LoopBatch.ARRAYS})

    def validate(self) -> None:
        _check_poses(self.odometry, "GraphSubmission")
        self.loops().validate()


@dataclass
class Estimate(Message):
    """The optimiser's global estimate: for robots `robots` [R] with `counts` [R] keyframes each, poses
    T_global_kf [sum(counts), 4, 4] robot after robot. The global frame is the odometry frame of robot `anchor`.
    `stamp` orders estimates (newer compares greater); `basis` maps robot id (str) -> graph version solved."""

    TYPE: ClassVar[int] = 7
    SCALARS: ClassVar[dict] = {"leader": int, "anchor": int, "stamp": list, "basis": dict, "formulation": str,
                               "solver": str}
    ARRAYS: ClassVar[dict] = {"robots": ("<i8", 1), "counts": ("<i8", 1), "poses": ("<f8", 3),
                              "scales": ("<f8", 1)}
    leader: int = 0
    anchor: int = 0
    stamp: list = field(default_factory=list)
    basis: dict = field(default_factory=dict)
    formulation: str = ""
    solver: str = ""
    robots: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))  # optimised loop scales (diagnostics)

    def per_robot(self) -> dict[int, np.ndarray]:
        out, off = {}, 0
        for r, c in zip(self.robots.tolist(), self.counts.tolist()):
            out[int(r)] = self.poses[off: off + c]
            off += c
        return out

    def validate(self) -> None:
        if len(self.robots) != len(self.counts) or np.any(self.counts < 0) or \
                int(self.counts.sum()) != len(self.poses) or self.poses.shape[1:] != (4, 4):
            raise MessageError("Estimate: robots, counts and poses disagree")
        _check_poses(self.poses, "Estimate")
        if not _ints(self.stamp):
            raise MessageError("Estimate: stamp must be a list of integers")


@dataclass
class Finish(Message):
    """The end protocol (`ending.py`), sent every tick from the schedule's last tick on, next to the hello.

    ready: 1 when the sender has no loop candidate left to verify and has exchanged descriptors and loops with
    every robot of its group; graph_version: as in Hello; estimate_stamp: the stamp of the estimate it holds;
    end: from the group's optimiser, the stamp of the final estimate (the mission is over for whoever holds it),
    from another robot, the same stamp echoed (it holds it and stops); [] until then.
    """

    TYPE: ClassVar[int] = 8
    SCALARS: ClassVar[dict] = {"tick": int, "ready": int, "graph_version": list, "estimate_stamp": list,
                               "end": list}
    tick: int = 0
    ready: int = 0
    graph_version: list = field(default_factory=list)
    estimate_stamp: list = field(default_factory=list)
    end: list = field(default_factory=list)

    def validate(self) -> None:
        if not (_ints(self.graph_version) and _ints(self.estimate_stamp) and _ints(self.end)) \
                or self.ready not in (0, 1):
            raise MessageError("Finish: versions and stamps must be lists of integers, ready 0 or 1")


@dataclass
class DistributedEstimate(Message):
    """The distributed solver's estimate for one neighbour (`swarm.solver: distributed`, distributed.py): a
    graph.distributed.messages.Estimate as its bytes, and `root`, the robot whose odometry frame its poses are in."""

    TYPE: ClassVar[int] = 9
    SCALARS: ClassVar[dict] = {"root": int}
    ARRAYS: ClassVar[dict] = {"blob": ("|u1", 1)}
    root: int = 0
    blob: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))

    def validate(self) -> None:
        from swarmsplat.graph.distributed.messages import Estimate as SolverEstimate

        if not 0 <= self.root <= 254:
            raise MessageError("DistributedEstimate: root must be a robot id")
        try:
            SolverEstimate.from_bytes(self.blob.tobytes())
        except InputError as e:
            raise MessageError(f"DistributedEstimate: {e}") from None


MESSAGE_TYPES: dict[int, type[Message]] = {
    c.TYPE: c for c in (Hello, Descriptors, EncodingRequest, EncodingReply, LoopBatch, GraphSubmission, Estimate,
                        Finish, DistributedEstimate)}


class Codec:
    """The wire format above for one family of messages: its magic, schema version and type registry. The
    swarm's messages use `SWARM` (the module-level `encode` / `decode` / `peek_header`); another family (the dense
    team's link, slam.run.team_link.messages) builds its own with another magic, so the two never mix."""

    def __init__(self, magic: bytes, version: int, types: dict[int, type[Message]]):
        if len(magic) != 4:
            raise InputError(f"a codec magic is 4 bytes, got {magic!r}")
        self.magic, self.version, self.types = magic, int(version), dict(types)

    def encode(self, msg: Message, sender: int, seq: int) -> bytes:
        """Message -> bytes (header + payload)."""
        if not 0 <= sender <= 254:
            raise InputError(f"sender robot id must be in 0..254, got {sender}")
        scalars = {k: getattr(msg, k) for k in msg.SCALARS}
        specs, blobs = [], []
        for name, (dt, ndim) in msg.ARRAYS.items():
            a = np.ascontiguousarray(getattr(msg, name), dtype=np.dtype(dt))
            if a.ndim != ndim:
                raise InputError(f"{msg.kind}.{name}: expected {ndim} dimensions, got shape {list(a.shape)}")
            specs.append([name, dt, list(a.shape)])
            blobs.append(a.tobytes())
        head = json.dumps({"s": scalars, "a": specs}, separators=(",", ":"), allow_nan=False).encode()
        payload = struct.pack("<I", len(head)) + head + b"".join(blobs)
        return _HEADER.pack(self.magic, self.version, msg.TYPE, sender, seq, len(payload)) + payload

    def peek_header(self, data: bytes) -> Header:
        """Check the header only (magic, version, type, exact length); MessageError when it is not ours."""
        if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < HEADER_BYTES:
            raise MessageError("message: shorter than a header")
        magic, ver, tid, sender, seq, n = _HEADER.unpack_from(bytes(data[:HEADER_BYTES]))
        if magic != self.magic:
            raise MessageError("message: foreign magic")
        if ver != self.version:
            raise MessageError(f"message: schema version {ver}, this robot speaks {self.version}")
        if tid not in self.types:
            raise MessageError(f"message: unknown type id {tid}")
        if n > MAX_PAYLOAD or HEADER_BYTES + n != len(data):
            raise MessageError(f"message: payload length {n} does not match the {len(data) - HEADER_BYTES} bytes "
                               f"given")
        return Header(tid, sender, seq)

    def decode(self, data: bytes) -> tuple[Header, Message]:
        """Bytes -> (Header, Message). Raises MessageError for anything that is not a valid message."""
        h = self.peek_header(data)
        return h, _decode_body(self.types[h.type_id], bytes(data)[HEADER_BYTES:])


def _decode_body(cls: type[Message], body: bytes) -> Message:
    if len(body) < 4:
        raise MessageError("message: payload too short")
    (n,) = struct.unpack_from("<I", body)
    if 4 + n > len(body):
        raise MessageError("message: JSON header runs past the payload")
    try:
        head = json.loads(body[4: 4 + n].decode("utf-8"))
        scalars, specs = head["s"], head["a"]
    except (ValueError, KeyError, TypeError, RecursionError):  # RecursionError: absurdly nested JSON
        raise MessageError(f"{cls.__name__}: corrupt JSON header") from None
    if not isinstance(scalars, dict) or set(scalars) != set(cls.SCALARS):
        raise MessageError(f"{cls.__name__}: expected fields {sorted(cls.SCALARS)}")
    kw = {}
    for k, typ in cls.SCALARS.items():
        v = scalars[k]
        if not isinstance(v, typ) or (typ is int and isinstance(v, bool)):
            raise MessageError(f"{cls.__name__}.{k}: expected {typ.__name__}, got {type(v).__name__}")
        kw[k] = v
    if not isinstance(specs, list) or [s[0] if isinstance(s, list) and len(s) == 3 else None for s in specs] \
            != list(cls.ARRAYS):
        raise MessageError(f"{cls.__name__}: expected arrays {list(cls.ARRAYS)}")
    off = 4 + n
    for (name, dt, shape), (want_dt, ndim) in zip(specs, cls.ARRAYS.values()):
        if dt != want_dt or dt not in _DTYPES or not isinstance(shape, list) or len(shape) != ndim \
                or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < (1 << 40) for d in shape):
            raise MessageError(f"{cls.__name__}.{name}: bad dtype or shape")
        size = int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
        if off + size > len(body):
            raise MessageError(f"{cls.__name__}.{name}: truncated")
        kw[name] = np.frombuffer(body, np.dtype(dt), count=size // np.dtype(dt).itemsize, offset=off).reshape(shape).copy()
        off += size
    if off != len(body):
        raise MessageError(f"{cls.__name__}: {len(body) - off} trailing bytes")
    msg = cls(**kw)
    if hasattr(msg, "validate"):
        msg.validate()
    assert {f.name for f in fields(msg)} == set(cls.SCALARS) | set(cls.ARRAYS)
    return msg


SWARM = Codec(MAGIC, SCHEMA_VERSION, MESSAGE_TYPES)
encode, peek_header, decode = SWARM.encode, SWARM.peek_header, SWARM.decode
