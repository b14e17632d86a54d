"""Drive one robot node on wall-clock ticks (a robot process): tick k starts at `start_time + k * tick_seconds`.

All robot processes of a run get the same `start_time`, so their ticks — and with them the rendezvous schedule
each enforces on its own links — agree to within the clock skew of one machine. A robot that falls behind
(a slow registration) skips the ticks it missed and runs the current one: its keyframes are read by tick, so
none is lost, and what arrived meanwhile waits in its inbox.
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


def run_clocked(step: Callable[[int], bool | None], ticks: int, start_time: float, tick_seconds: float,
                clock: TickClock | None = None) -> int:
    """Call `step(tick)` at the wall-clock start of each tick in 0 .. ticks-1 until it returns True, skipping
    ticks already over (the last tick always runs). Returns the number of ticks skipped."""
    tick, skipped = 0, 0
    while tick < ticks:
        wait = start_time + tick * tick_seconds - time.time()
        if wait > 0:
            time.sleep(wait)
        now = min(ticks - 1, max(tick, int((time.time() - start_time) // tick_seconds)))
        skipped += now - tick
        tick = now
        if clock is not None:
            clock.tick = tick
        if step(tick):
            break
        tick += 1
    return skipped
