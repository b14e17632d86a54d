"""How robot nodes exchange messages: the `Transport` interface and its deterministic in-process implementation.

A transport belongs to one robot. `send(dest, msg)` publishes to one robot (`dest` an id) or to every robot in
range (`dest=None`); `poll()` returns the valid messages that have arrived, dropping (and counting) anything that
does not decode. Bytes are counted per message type, sent and received, on every transport, and per peer robot
(`peer_stats`). A transport speaks one message family (`codec`, the swarm's by default).

`InProcessNetwork` is the simulated radio shared by all robots of one process. Time advances in ticks
(`network.advance(tick)`); a message is delivered at a tick >= its send tick + delay, only while the two robots
are linked (the rendezvous schedule, plus links forced down) and neither is killed. Faults are injected
deterministically from a seed: drop, duplicate, delay, reorder, link down/up, killed robots, raw bytes.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from . import messages as M
from .rendezvous import Schedule


@dataclass
class ByteCounter:
    """Bytes and counts per message type, sent and received; `rejected` counts buffers that did not decode."""

    sent_bytes: dict = field(default_factory=lambda: defaultdict(int))
    sent_count: dict = field(default_factory=lambda: defaultdict(int))
    recv_bytes: dict = field(default_factory=lambda: defaultdict(int))
    recv_count: dict = field(default_factory=lambda: defaultdict(int))
    rejected: int = 0

    def on_send(self, kind: str, n: int) -> None:
        self.sent_bytes[kind] += n
        self.sent_count[kind] += 1

    def on_recv(self, kind: str, n: int) -> None:
        self.recv_bytes[kind] += n
        self.recv_count[kind] += 1

    def to_dict(self) -> dict:
        return {"sent_bytes": dict(self.sent_bytes), "sent_count": dict(self.sent_count),
                "recv_bytes": dict(self.recv_bytes), "recv_count": dict(self.recv_count),
                "sent_total": int(sum(self.sent_bytes.values())), "rejected": self.rejected}


class Transport(ABC):
    """One robot's end of the link."""

    def __init__(self, robot: int, codec: M.Codec | None = None):
        self.robot = int(robot)
        self.codec = codec or M.SWARM
        self.stats = ByteCounter()
        self.peer_stats: dict[int, ByteCounter] = defaultdict(ByteCounter)  # per robot: to it (direct) / from it
        self.team: set[int] | None = None  # the robots of this run (a subclass sets it): others' messages are foreign
        self._seq = 0

    def send(self, dest: int | None, msg: M.Message) -> int:
        """Publish `msg` to robot `dest` (None: every robot in range). Returns the bytes put on the link."""
        self._seq += 1
        data = self.codec.encode(msg, self.robot, self._seq)
        self.stats.on_send(msg.kind, len(data))
        if dest is not None:
            self.peer_stats[int(dest)].on_send(msg.kind, len(data))
        self._send_bytes(dest, data)
        return len(data)

    def poll(self) -> list[tuple[M.Header, M.Message]]:
        """Valid messages received since the last poll, in arrival order; invalid buffers and messages from robots
        outside the team are counted (`stats.rejected`) and dropped."""
        out = []
        for data in self._receive_bytes():
            try:
                h, msg = self.codec.decode(data)
            except M.MessageError:
                self.stats.rejected += 1
                continue
            if h.sender == self.robot:
                continue
            if self.team is not None and h.sender not in self.team:  # another team's robot: foreign
                self.stats.rejected += 1
                continue
            self.stats.on_recv(msg.kind, len(data))
            self.peer_stats[h.sender].on_recv(msg.kind, len(data))
            out.append((h, msg))
        return out

    @abstractmethod
    def neighbours(self) -> list[int]:
        """Robots this one can reach now, as the link layer sees it (nodes rely on heartbeats instead)."""

    @abstractmethod
    def _send_bytes(self, dest: int | None, data: bytes) -> None: ...

    @abstractmethod
    def _receive_bytes(self) -> list[bytes]: ...

    def close(self) -> None:
        """Release resources (sessions, sockets)."""


@dataclass
class Faults:
    """Random faults applied to every message, drawn from `seed` (deterministic for a given run).

    drop / duplicate: probabilities per delivery; delay: (min, max) extra ticks, uniform; reorder: shuffle
    the messages that become deliverable at the same tick (with delay, messages overtake each other).
    """

    drop: float = 0.0
    duplicate: float = 0.0
    delay: tuple[int, int] = (0, 0)
    reorder: bool = False
    seed: int = 0


@dataclass(order=True)
class _InFlight:
    deliver: int
    order: float
    dest: int = field(compare=False)
    src: int = field(compare=False)
    data: bytes = field(compare=False)


class InProcessNetwork:
    """The simulated radio between the robots of one process (see the module docstring)."""

    def __init__(self, robots, schedule: Schedule | None = None, faults: Faults | None = None):
        self.robots = sorted(int(r) for r in robots)
        self.schedule = schedule
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(self.faults.seed)
        self.tick = 0
        self.killed: set[int] = set()
        self.down: set[frozenset] = set()
        self._flight: list[_InFlight] = []
        self._inbox: dict[int, list[bytes]] = {r: [] for r in self.robots}
        self._n = 0

    def endpoint(self, robot: int, codec: M.Codec | None = None) -> "InProcessTransport":
        return InProcessTransport(self, robot, codec)

    # ------------------------------------------------------------------------------------- faults
    def kill(self, robot: int) -> None:
        """The robot vanishes: nothing to or from it is delivered, messages already queued for it are lost."""
        self.killed.add(int(robot))
        self._inbox[int(robot)] = []

    def revive(self, robot: int) -> None:
        self.killed.discard(int(robot))

    def link_down(self, a: int, b: int) -> None:
        self.down.add(frozenset((int(a), int(b))))

    def link_up(self, a: int, b: int) -> None:
        self.down.discard(frozenset((int(a), int(b))))

    def inject(self, dest: int, data: bytes) -> None:
        """Deliver raw bytes (a foreign or malformed message) to `dest` at the next poll."""
        self._inbox[int(dest)].append(bytes(data))

    # ------------------------------------------------------------------------------------- links
    def linked(self, a: int, b: int) -> bool:
        if a in self.killed or b in self.killed or frozenset((a, b)) in self.down:
            return False
        return True if self.schedule is None else self.schedule.linked(self.tick, a, b)

    def neighbours(self, robot: int) -> list[int]:
        """Robots `robot` can reach now (what a radio would report; nodes rely on heartbeats instead)."""
        return [r for r in self.robots if r != robot and self.linked(robot, r)]

    def _post(self, src: int, dest: int | None, data: bytes) -> None:
        if src in self.killed:
            return
        f = self.faults
        for d in (self.robots if dest is None else [int(dest)]):
            if d == src or d not in self._inbox or not self.linked(src, d):
                continue
            copies = 1 + int(f.duplicate > 0 and self.rng.random() < f.duplicate)
            for _ in range(copies):
                if f.drop > 0 and self.rng.random() < f.drop:
                    continue
                delay = int(self.rng.integers(f.delay[0], f.delay[1] + 1)) if f.delay[1] > 0 else 0
                order = float(self.rng.random()) if f.reorder else float(self._n)
                self._n += 1
                self._flight.append(_InFlight(self.tick + delay, order, d, src, data))

    def advance(self, tick: int) -> None:
        """Move time to `tick` and hand every message due by then to its receiver's inbox (in delivery order);
        messages whose link is down at delivery time are lost."""
        self.tick = int(tick)
        due = sorted(m for m in self._flight if m.deliver <= self.tick)
        self._flight = [m for m in self._flight if m.deliver > self.tick]
        for m in due:
            if self.linked(m.src, m.dest):
                self._inbox[m.dest].append(m.data)

    def _take(self, robot: int) -> list[bytes]:
        if robot in self.killed:
            return []
        out, self._inbox[robot] = self._inbox[robot], []
        return out


class InProcessTransport(Transport):
    """A robot's endpoint on an `InProcessNetwork`. Messages sent during a tick arrive at the next `advance`."""

    def __init__(self, network: InProcessNetwork, robot: int, codec: M.Codec | None = None):
        super().__init__(robot, codec)
        self.network = network
        self.team = set(network.robots)

    def neighbours(self) -> list[int]:
        return [] if self.robot in self.network.killed else self.network.neighbours(self.robot)

    def _send_bytes(self, dest: int | None, data: bytes) -> None:
        self.network._post(self.robot, dest, data)

    def _receive_bytes(self) -> list[bytes]:
        return self.network._take(self.robot)
