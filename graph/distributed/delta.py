"""Separator poses relative to an earlier estimate: what each robot keeps so that its estimates can carry float16
twists (12 bytes a pose) instead of absolute float32 poses (24 bytes) (graph.distributed.messages, FLAG_DELTA).

A robot sends a neighbour relative poses only from an estimate the neighbour said it holds: every estimate carries
`ack`, the newest stamp of the recipient's estimates the sender holds, and the recipient's next estimate to it
starts from that one. Both sides remember what the recipient decoded for each recent stamp (the sender computes it
the same way), so the twist is always taken from the recipient's own copy: float16's rounding (2^-11 of each
component) stays in one estimate and never accumulates, and it shrinks as the team converges and the twists
shrink. Lost, duplicated and reordered estimates are harmless: an estimate whose base the recipient does not hold
is dropped like a lost one and the sender, still acked with an older stamp, starts from that; with no ack, or a
twist float16 cannot hold, the estimate goes absolute. A resend of one stamp carries the same bytes.

GNC weights, which change only when a robot updates them, are left out (FLAG_WEIGHTS_HELD) once the recipient has
acked an estimate that carried the current ones: every estimate it took since then carried the same.
"""

from __future__ import annotations

import numpy as np

from .. import lie
from .messages import DELTA_BYTES, FLAG_DELTA, FLAG_SPARSE, FLAG_WEIGHTS_HELD, Estimate, as_sent

HISTORY = 16  # stamps remembered per neighbour, on each side
F16_MAX = 6.0e4  # twists beyond this (float16's range ends at 65504) go absolute


def moved(base: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The poses the recipient decodes: `base` [P, 4, 4] moved by the twists `delta` [P, 6]."""
    return base @ lie.exp(delta)


def _trim(hist: dict) -> None:
    for s in sorted(hist)[:-HISTORY]:
        del hist[s]


class Sent:
    """The sending side, per recipient: what it decoded for each recent stamp, the newest ack it sent back, and the
    encoding made for the latest stamp."""

    def __init__(self, tol: tuple[float, float] = (0.0, 0.0)):
        """`tol`: (rotation in radians, translation in the graph's units): a twist whose every rotation and every
        translation component is below these is sent as zero (the recipient keeps its copy)."""
        self.tol = tol
        self.decoded: dict[int, dict[int, tuple[tuple, np.ndarray]]] = {}  # recipient -> stamp -> (keys, poses)
        self.acked: dict[int, tuple[int, int]] = {}  # recipient -> (its stamp the ack came with, the ack)
        self.made: dict[int, tuple[int, tuple, int, np.ndarray | None]] = {}  # recipient -> (stamp, keys, base, delta)
        self.weights: dict[int, tuple[tuple, int]] = {}  # recipient -> (weights, the first stamp that sent them)

    def heard(self, q: int, stamp: int, ack: int) -> None:
        """`q`'s estimate `stamp` says it holds our estimate `ack`."""
        if stamp >= self.acked.get(q, (-1, -1))[0]:
            self.acked[q] = (stamp, ack)

    def encode(self, msg: Estimate, keys: tuple) -> None:
        """Make `msg` (absolute poses of `keys`) relative where the recipient holds a base."""
        q = msg.recipient
        made = self.made.get(q)
        if made is None or made[0] != msg.stamp or made[1] != keys:
            hist = self.decoded.setdefault(q, {})
            ack = self.acked.get(q, (-1, -1))[1]
            base, delta = -1, None
            if keys and ack in hist and hist[ack][0] == keys:
                d = lie.log(lie.between(hist[ack][1], msg.poses))
                if np.all(np.isfinite(d)) and np.abs(d).max() < F16_MAX:
                    a = np.abs(d)
                    d[(a[:, :3].max(1) < self.tol[0]) & (a[:, 3:].max(1) < self.tol[1])] = 0.0
                    base, delta = ack, d.astype("<f2").astype(np.float64)
            hist[msg.stamp] = (keys, as_sent(msg.poses) if delta is None else moved(hist[base][1], delta))
            _trim(hist)
            made = self.made[q] = (msg.stamp, keys, base, delta)
        if made[3] is not None:
            msg.flags |= FLAG_DELTA
            msg.base, msg.delta = made[2], made[3]
            moving = int(np.any(made[3] != 0, axis=1).sum())
            if (len(made[3]) + 7) // 8 < (len(made[3]) - moving) * DELTA_BYTES:
                msg.flags |= FLAG_SPARSE

    def encode_weights(self, msg: Estimate) -> None:
        """Leave `msg`'s weights out where the recipient holds them (module docstring)."""
        q, w = msg.recipient, tuple(msg.weights.tolist())
        held = self.weights.get(q)
        if held is None or held[0] != w or held[1] > msg.stamp:
            self.weights[q] = held = (w, msg.stamp)
        if len(w) and self.acked.get(q, (-1, -1))[1] >= held[1]:
            msg.flags |= FLAG_WEIGHTS_HELD
            msg.weights = np.zeros(0)


class Received:
    """The receiving side, per sender: the poses decoded for each recent stamp."""

    def __init__(self):
        self.decoded: dict[int, dict[int, tuple[tuple, np.ndarray]]] = {}  # sender -> stamp -> (keys, poses)

    def ack(self, q: int) -> int:
        """The newest stamp of `q`'s estimates held (-1: none)."""
        hist = self.decoded.get(q)
        return max(hist) if hist else -1

    def decode(self, msg: Estimate, keys: tuple) -> bool:
        """Fill a relative `msg`'s poses from its base; remember what was decoded. False: the base is not held
        (or was of other keys): the estimate cannot be used."""
        hist = self.decoded.setdefault(msg.sender, {})
        if msg.flags & FLAG_DELTA:
            b = hist.get(msg.base)
            if b is None or b[0] != keys or len(msg.delta) != len(keys):
                return False
            msg.poses = moved(b[1], msg.delta)
        if keys and len(msg.poses) == len(keys):
            hist[msg.stamp] = (keys, msg.poses)
            _trim(hist)
        return True
