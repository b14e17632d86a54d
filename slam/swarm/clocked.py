"""Drive one robot node on wall-clock ticks (a robot process): tick k starts at `start_time + k * tick_seconds`.

All robot processes of a run get the same `start_time`, so their ticks — and with them the rendezvous schedule
each enforces on its own links — agree to within the clock skew of one machine. A robot that falls behind
(a slow registration) simply runs the ticks it missed back to back.
"""

from __future__ import annotations

import time
from typing import Callable


class TickClock:
    """The current tick of a robot process (read by the Zenoh transport to gate links)."""

    def __init__(self) -> None:
        self.tick = 0

    def __call__(self) -> int:
        return self.tick


def run_clocked(step: Callable[[int], None], ticks: int, start_time: float, tick_seconds: float,
                clock: TickClock | None = None) -> None:
    """Call `step(tick)` for tick = 0 .. ticks-1, each no earlier than its wall-clock start."""
    for tick in range(ticks):
        wait = start_time + tick * tick_seconds - time.time()
        if wait > 0:
            time.sleep(wait)
        if clock is not None:
            clock.tick = tick
        step(tick)
