"""Which waiting frame the tracker takes and which it drops as `stale`, from what the stream measured.

A frame's pose latency is its wait (arrival to the tracker taking it) plus the tracker's time to its pose. The
scheduler keeps the median of both over the last `window` frames: the pose time of a tracked frame, and the
hand-off delay of a fresh frame (one that arrived while the tracker was free: the reader's lateness and the
thread's wake-up, what a frame waits at least). A frame is dropped as stale when its wait plus the expected pose
time passes the budget while a fresh frame's (the expected hand-off plus the expected pose time) does not:
dropping it lets the next frame be posed in time. When a fresh frame cannot make
the budget either, every frame is tracked, late.

Every fresh frame adds a hand-off sample, dropped ones included, and a frame is only dropped when its wait
exceeds what the budget leaves after the expected pose time: each fresh frame dropped adds a sample above that,
so after at most `window` of them in a row the hand-off estimate is above it too and the rule stops dropping. (A
frame that waited in the queue behind a busy tracker adds no sample; the queue's length bounds those.) The
decision never freezes on figures that the drops keep from being measured again. Times are in seconds on one
monotonic clock that the caller passes in (tests drive it with a fake one).
"""

from __future__ import annotations

import collections
import statistics


class Scheduler:
    def __init__(self, budget_s: float, *, window: int = 20):
        self.budget = budget_s
        self._pose: collections.deque[float] = collections.deque(maxlen=window)  # s, take -> pose
        self._handoff: collections.deque[float] = collections.deque(maxlen=window)  # s, a fresh frame's wait
        self._free_at = float("-inf")  # when the tracker last finished with a frame (`free`)

    def expected_pose_s(self) -> float:
        """The median time from taking a frame to its pose over the last frames tracked (0 before the first)."""
        return statistics.median(self._pose) if self._pose else 0.0

    def expected_handoff_s(self) -> float:
        """The median hand-off delay over the last frames taken (0 before the first)."""
        return statistics.median(self._handoff) if self._handoff else 0.0

    def take(self, now: float, due: float) -> str | None:
        """A frame that arrived at `due` is taken at `now`: None to track it, or the reason to drop it
        ("stale"). Before the first pose nothing is dropped (no estimate yet)."""
        if due >= self._free_at:  # arrived while the tracker was free: a fresh frame
            self._handoff.append(max(0.0, now - due))
        if not self._pose:
            return None
        pose = self.expected_pose_s()
        if now - due + pose > self.budget >= self.expected_handoff_s() + pose:
            return "stale"
        return None

    def posed(self, taken: float, posed: float) -> None:
        """The frame taken at `taken` got its pose at `posed`."""
        self._pose.append(posed - taken)

    def free(self, now: float) -> None:
        """The tracker is done with its frame (dropped, or posed and its keyframe handed over) and waits for the
        next."""
        self._free_at = now
