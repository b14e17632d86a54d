"""One robot of the distributed pose-graph solver (graph.distributed) on the swarm's transport.

The same per-robot state and step as the simulated team; what this adds is the schedule without a shared clock.
A robot of colour c steps in round k once it holds round k's estimate of every neighbour of a lower colour and
round k-1's of every neighbour of a higher colour: exactly what it holds in the simulated team, so the two give
the same estimates. A neighbour silent for `timeout_s` is taken as gone (its last estimate stays held) until it
speaks again; the robot resends its latest estimate every `resend_s` while it waits (idempotent: receivers keep
the newest stamp), so a lost message only delays, and shows it is alive: only a neighbour that sends nothing at
all for `timeout_s` is taken as gone, so a robot waiting for a third one holds up its neighbours without being
given up. Estimates travel as `graph.distributed.messages.Estimate`
bytes inside a message of their own codec family (magic DPGS), never mixed with the swarm's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from swarmsplat.graph.distributed.messages import Estimate
from swarmsplat.graph.distributed.robot import RobotSolver
from swarmsplat.kernels.errors import InputError

from .messages import Codec, Message, MessageError


@dataclass
class SolverEstimate(Message):
    """A `graph.distributed.messages.Estimate`, as its bytes."""

    TYPE: ClassVar[int] = 1
    ARRAYS: ClassVar[dict] = {"blob": ("|u1", 1)}
    blob: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))

    def validate(self) -> None:
        try:
            Estimate.from_bytes(self.blob.tobytes())
        except InputError as e:
            raise MessageError(f"SolverEstimate: {e}") from None


CODEC = Codec(b"DPGS", 1, {SolverEstimate.TYPE: SolverEstimate})


def transport_id(robot: int) -> int:
    """Transport id (0, 1, ...) of a robot named by its Symbol character code ('a' = 97 -> 0)."""
    return robot - ord("a")


def run_solver_robot(solver: RobotSolver, transport, colours: dict[int, int], rounds: int, *,
                     timeout_s: float = 3.0, start_timeout_s: float = 30.0, resend_s: float = 0.25,
                     linger_s: float = 1.0, on_round=None) -> dict:
    """Run `rounds` rounds of `solver` over `transport` (module docstring); returns counts for the summary.
    Before round 1 the robot waits up to `start_timeout_s` for every neighbour's initial estimate (processes
    start at different speeds); after that a neighbour silent for `timeout_s` is taken as gone."""
    me = solver.robot
    last: list[Estimate] = solver.messages(scalars=False)
    gone: set[int] = set()
    heard: dict[int, float] = {}  # neighbour -> when we last heard it (a resent, stale estimate is proof of life)
    timeouts = 0

    def send(msgs):
        for m in msgs:
            if m.recipient in gone:  # nothing to a robot taken as gone until it speaks again
                continue
            transport.send(transport_id(m.recipient), SolverEstimate(np.frombuffer(m.to_bytes(), np.uint8)))

    def take():
        for _, msg in transport.poll():
            if isinstance(msg, SolverEstimate):
                est = Estimate.from_bytes(msg.blob.tobytes())
                heard[est.sender] = time.monotonic()
                if solver.receive(est):
                    gone.discard(est.sender)

    send(last)
    for k in range(1, rounds + 1):
        need = {q: k if colours[q] < colours[me] else k - 1 for q in solver.part.neighbours}
        wait_s = start_timeout_s if k == 1 else timeout_s
        t_wait = t_sent = time.monotonic()
        while True:
            take()
            missing = [q for q, s in need.items() if q not in gone and solver.nb_stamp.get(q, -1) < s]
            if not missing:
                break
            now = time.monotonic()
            silent = [q for q in missing if now - max(t_wait, heard.get(q, t_wait)) > wait_s]
            if silent:  # a neighbour that still resends is alive (it waits for someone else): keep waiting for it
                gone.update(silent)
                timeouts += 1
                continue
            if now - t_sent > resend_s:
                send(last)
                t_sent = now
            time.sleep(0.002)
        last = solver.step()
        send(last)
        if on_round:
            on_round(k)
    t_end = time.monotonic() + linger_s  # neighbours may still wait for our last estimate: resend it a while
    while time.monotonic() < t_end:
        take()
        time.sleep(resend_s)
        send(last)
    return {"rounds": rounds, "timeouts": timeouts, "gone": sorted(gone)}
