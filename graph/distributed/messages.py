"""What robots of the distributed solver send each other: one `Estimate` per neighbour per step, as bytes.

An estimate carries only what its recipient needs: the sender's separator poses (those the recipient's loops
touch), the scales of the loops the two share, the GNC weights of those the sender owns, and a few team-wide
scalars (the shared scale's consensus terms, GNC's mu). Nothing is named on the wire: both robots of a pair derive
the same lists from the loops they share (`partition.RobotPart.separators` and `pair_loops`), so poses come in
the order of the sender's separator list for the recipient, scales in the order of the pair's up-to-scale loops
and weights in that of the pair's loops the sender owns (only when GNC runs).

Wire format (little-endian, no pickle): a 25-byte header (magic, sender, recipient, stamp, base, ack, counts,
flags), then the poses, scales and weights as float32, and with FLAG_SCALARS four float64 and a uint32 stamp, then
a uint16 count of relayed terms, each robot (uint8), stamp (uint32), g and H (float64): the shared scale's terms of
robots that are not the recipient's neighbours.

Poses come one of two ways. Absolute (FLAG_DELTA clear): 6 float32 each (rotation vector, translation), 24 bytes;
float32 rounds a position 1 km from the origin by ~30 µm, far below any loop's noise. Relative (FLAG_DELTA): 6
float16 each, 12 bytes, the twist `log(B^-1 T)` from the pose B the recipient decoded from the sender's estimate
stamped `base`, which the recipient said it holds (`ack` of its own estimates); graph.distributed.delta keeps
both sides' histories and decodes, so the recipient's copy is its base moved by the rounded twist and the next
twist is taken from that copy (the rounding never accumulates). The sender keeps its own estimate in float64.
Twists too small to matter (graph.distributed.delta.Sent's tolerance) are sent as zero; when that saves bytes the
estimate is sparse (FLAG_SPARSE): a bit per pose (ceil(P / 8) bytes, bit i of byte i // 8 from the lowest) tells
which twists follow, the others are zero (the recipient's copy stays its base). Bytes that do not decode raise
InputError; the transport drops them, and a robot drops an estimate whose counts
are not those it expects or whose base it does not hold.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels.errors import InputError

from .. import lie

MAGIC = b"DPG2"
_HEAD = struct.Struct("<4sBBIiiHHHB")  # magic, sender, recipient, stamp, base, ack, poses, scales, weights, flags
_SCALARS = struct.Struct("<ddddI")
_COUNT = struct.Struct("<H")
_RELAYED = struct.Struct("<BIdd")  # robot, the stamp of its terms, its shared-scale g and H
FLAG_SCALARS = 1  # the consensus scalars follow
FLAG_STILL = 2  # the sender's last step moved its poses by less than the tolerance
FLAG_BINARY = 4  # every GNC weight the sender owns is 0 or 1
FLAG_DELTA = 8  # the poses are float16 twists from the sender's estimate `base` (module docstring)
FLAG_WEIGHTS_HELD = 16  # no weights: the recipient holds the sender's current ones (graph.distributed.delta)
FLAG_SPARSE = 32  # with FLAG_DELTA: a bit per pose, then the twists of the set bits only (the others are zero)
POSE_BYTES = 24  # an absolute pose
DELTA_BYTES = 12  # a pose relative to a base
COUNT_MAX = 0xFFFF


@dataclass
class Estimate:
    sender: int  # robot number (Symbol character's code)
    recipient: int
    stamp: int  # the sender's step counter: newer estimates compare greater
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # [P, 4, 4] T_world_kf
    scales: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [S]
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [W]
    flags: int = 0
    # consensus scalars (FLAG_SCALARS): this robot's shared-scale gradient and Gauss-Newton curvature, the shared
    # scale it holds with its stamp, and its proposal for GNC's initial mu
    shared_g: float = 0.0
    shared_h: float = 0.0
    shared_s: float = 0.0
    mu0: float = 0.0
    shared_stamp: int = 0
    relayed: list = field(default_factory=list)  # [(robot, stamp, g, H)]: other robots' terms, passed on
    base: int = -1  # FLAG_DELTA: the stamp of the sender's estimate the twists start from
    ack: int = -1  # the newest stamp of the recipient's estimates the sender holds (-1: none)
    delta: np.ndarray | None = None  # FLAG_DELTA: [P, 6] twists (float16 values); `poses` is then empty until
    # the recipient decodes them (graph.distributed.delta.Received). With FLAG_SPARSE only the rows that are not
    # zero go on the wire, after a bit mask of them.

    def to_bytes(self) -> bytes:
        S, W = len(self.scales), len(self.weights)
        if self.flags & FLAG_DELTA:
            P = len(self.delta)
            d = np.asarray(self.delta, "<f2")
            if self.flags & FLAG_SPARSE:
                rows = np.any(d != 0, axis=1)
                body = np.packbits(rows, bitorder="little").tobytes() + d[rows].tobytes()
            else:
                body = d.tobytes()
        else:
            P = len(self.poses)
            body = np.asarray(_wire(self.poses), "<f4").tobytes()
        if max(P, S, W) > COUNT_MAX:
            raise InputError(f"distributed estimate: {max(P, S, W)} poses, scales or weights for one neighbour, "
                             f"at most {COUNT_MAX}")
        out = [_HEAD.pack(MAGIC, self.sender, self.recipient, self.stamp, self.base, self.ack, P, S, W, self.flags),
               body, np.asarray(self.scales, "<f4").tobytes(), np.asarray(self.weights, "<f4").tobytes()]
        if self.flags & FLAG_SCALARS:
            out.append(_SCALARS.pack(self.shared_g, self.shared_h, self.shared_s, self.mu0, self.shared_stamp))
            out.append(_COUNT.pack(len(self.relayed)))
            out += [_RELAYED.pack(*r) for r in self.relayed]
        return b"".join(out)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Estimate":
        if len(data) < _HEAD.size:
            raise InputError(f"distributed estimate: {len(data)} bytes, shorter than its header")
        magic, sender, recipient, stamp, base, ack, P, S, W, flags = _HEAD.unpack_from(data)
        if magic != MAGIC:
            raise InputError("distributed estimate: wrong magic")
        delta = bool(flags & FLAG_DELTA)
        if delta and base < 0:
            raise InputError("distributed estimate: relative poses without a base")
        sparse = bool(flags & FLAG_SPARSE)
        if sparse and not delta:
            raise InputError("distributed estimate: a pose mask without relative poses")
        rows = None
        if sparse:
            nmask = (P + 7) // 8
            if len(data) < _HEAD.size + nmask:
                raise InputError(f"distributed estimate: {len(data)} bytes, shorter than its pose mask")
            bits = np.unpackbits(np.frombuffer(data, np.uint8, nmask, _HEAD.size), bitorder="little")
            if bits[P:].any():
                raise InputError("distributed estimate: pose mask bits beyond its poses")
            rows = bits[:P].astype(bool)
            size = _HEAD.size + nmask + int(rows.sum()) * DELTA_BYTES + 4 * (S + W)
        else:
            size = _HEAD.size + P * (DELTA_BYTES if delta else POSE_BYTES) + 4 * (S + W)
        n_relayed = 0
        if flags & FLAG_SCALARS:
            size += _SCALARS.size + _COUNT.size
            if len(data) >= size:
                n_relayed = _COUNT.unpack_from(data, size - _COUNT.size)[0]
                size += n_relayed * _RELAYED.size
        if len(data) != size:
            raise InputError(f"distributed estimate: {len(data)} bytes, expected {size}")
        o = _HEAD.size + ((P + 7) // 8 if sparse else 0)
        buf = memoryview(data)

        def take(dtype, n):
            nonlocal o
            a = np.frombuffer(buf[o:o + np.dtype(dtype).itemsize * n], dtype).copy()
            o += a.nbytes
            return a

        if sparse:
            xi = np.zeros((P, 6))
            xi[rows] = take("<f2", 6 * int(rows.sum())).reshape(-1, 6).astype(np.float64)
        else:
            xi = take("<f2" if delta else "<f4", 6 * P).reshape(P, 6).astype(np.float64)
        s, w = take("<f4", S).astype(np.float64), take("<f4", W).astype(np.float64)
        if not (np.all(np.isfinite(xi)) and np.all(np.isfinite(s)) and np.all(np.isfinite(w))):
            raise InputError("distributed estimate: non-finite value")
        if delta:
            msg = cls(sender, recipient, stamp, np.zeros((0, 4, 4)), s, w, flags, base=base, ack=ack, delta=xi)
        else:
            msg = cls(sender, recipient, stamp, absolute_poses(xi), s, w, flags, base=base, ack=ack)
        if flags & FLAG_SCALARS:
            msg.shared_g, msg.shared_h, msg.shared_s, msg.mu0, msg.shared_stamp = _SCALARS.unpack_from(data, o)
            o += _SCALARS.size + _COUNT.size
            msg.relayed = [_RELAYED.unpack_from(data, o + i * _RELAYED.size) for i in range(n_relayed)]
            if not all(np.isfinite(r[2:]).all() for r in msg.relayed):
                raise InputError("distributed estimate: non-finite value")
        return msg


def absolute_poses(xi: np.ndarray) -> np.ndarray:
    """[P, 6] (rotation vector, translation) -> [P, 4, 4]."""
    T = np.tile(np.eye(4), (len(xi), 1, 1))
    T[:, :3, :3] = lie.so3_exp(xi[:, :3])
    T[:, :3, 3] = xi[:, 3:]
    return T


def _wire(poses: np.ndarray) -> np.ndarray:
    """[P, 4, 4] -> [P, 6] (rotation vector, translation): an absolute pose as the wire carries it."""
    if not len(poses):
        return np.zeros((0, 6))
    return np.concatenate([lie.so3_log(poses[:, :3, :3]), poses[:, :3, 3]], 1)


def as_sent(poses: np.ndarray) -> np.ndarray:
    """The poses exactly as the recipient decodes them from an absolute estimate (float32 on the wire)."""
    return absolute_poses(np.asarray(_wire(poses), "<f4").astype(np.float64))
