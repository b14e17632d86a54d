"""The sensor of a real-time run: a sequence's frames replayed at their timestamps (or at a fixed rate) into a
bounded queue, as a camera driver hands frames over.

A reader thread decodes each frame ahead of its arrival time (and converts it for the agent: `prepare`), then
puts it in the queue at that time; a reader that fell a whole frame behind skips to the frame due now (dropped,
reason "reader_late"), so its lag never grows. A frame that arrives at a full queue pushes the oldest waiting
frame out (dropped, reason "queue_full"), so nothing queues without bound. Arrival times are `time.monotonic()` values: a frame's pose latency is measured from the moment
it was due, so a reader that decodes too slowly shows up as latency, not as a faster sensor.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.errors import InputError

from ..guard import read_frame


@dataclass
class Arrival:
    frame: object  # slam.io.datasets Frame: index, timestamp, color, depth
    due: float  # time.monotonic() at which it arrived
    prepared: object = None  # what the feed's `prepare` made of it (None without one)


def arrival_offsets(timestamps: np.ndarray, n: int, rate: float) -> tuple[np.ndarray, float]:
    """(seconds after the first frame at which each of the first n frames arrives, the frame interval in s): at
    `rate` Hz, or (rate 0) at the sequence's own timestamps. InputError when rate is 0 and the timestamps do not
    increase."""
    if rate > 0:
        return np.arange(n) / rate, 1.0 / rate
    t = np.asarray(timestamps[:n], dtype=np.float64) - float(timestamps[0])
    steps = np.diff(t)
    if n > 1 and not np.all(steps > 0):
        raise InputError("the sequence's timestamps do not increase, so it has no rate of its own to replay at: "
                         "give one with --rate HZ (runtime.rate)")
    return t, float(np.median(steps)) if n > 1 else 0.0


class FrameFeed:
    """Frames 0..n-1 of `seq` arriving at `offsets` (s after `start`) into a queue of at most `queue` frames.
    `skipper.skip_frame` records an unreadable frame (slam.run.guard.read_frame; strict: the error stops the run,
    raised from `take`). `prepare(frame)`, if given, runs on the reader's thread before the frame is due, as a
    camera driver converts its images (Arrival.prepared); when it returns None the frame does not arrive (it
    recorded why, as the skipper does)."""

    def __init__(self, seq, offsets: np.ndarray, *, queue: int, skipper, strict: bool = False, prepare=None):
        self.seq, self.offsets, self.size = seq, offsets, queue
        self.skipper, self.strict, self.prepare = skipper, strict, prepare
        self._q: collections.deque[Arrival] = collections.deque()
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._error: BaseException | None = None
        self.arrived = 0  # frames that reached the queue
        self.dropped: list[tuple[int, str]] = []  # (frame index, reason), in the order they were dropped
        self.late: list[float] = []  # s by which the reader delivered a frame after it was due (decoding too slow)
        self.start_time = 0.0
        self._thread = threading.Thread(target=self._run, name="realtime-feed", daemon=True)

    def start(self, lead: float = 0.05) -> None:
        """Start the replay: the first frame arrives `lead` seconds from now."""
        self.start_time = time.monotonic() + lead
        self._thread.start()

    def _run(self) -> None:
        try:
            n = len(self.offsets)
            for i in range(n):
                if self._stop.is_set():
                    break
                if i + 1 < n and time.monotonic() >= self.start_time + float(self.offsets[i + 1]):
                    self.dropped.append((i, "reader_late"))  # a newer frame is due already: skip to it
                    continue
                f = read_frame(self.seq, i, self.skipper, strict=self.strict)  # decoded before it is due
                ready = None if f is None or self.prepare is None else self.prepare(f)
                due = self.start_time + float(self.offsets[i])
                if self._stop.wait(max(0.0, due - time.monotonic())):
                    break
                self.late.append(max(0.0, time.monotonic() - due))
                if f is None or (self.prepare is not None and ready is None):
                    continue
                with self._cv:
                    if len(self._q) >= self.size:
                        self.dropped.append((int(self._q.popleft().frame.index), "queue_full"))
                    self._q.append(Arrival(f, due, ready))
                    self.arrived += 1
                    self._cv.notify()
        except BaseException as e:  # noqa: BLE001 - handed to the tracker's thread, which raises it
            self._error = e
        finally:
            with self._cv:
                self._done = True
                self._cv.notify()

    def take(self) -> Arrival | None:
        """The oldest waiting frame, waiting for one to arrive; None once the replay has ended and the queue is
        empty (or the feed was stopped)."""
        with self._cv:
            while not self._q and not self._done and not self._stop.is_set():
                self._cv.wait(0.1)
            if self._error is not None:
                raise self._error
            if self._stop.is_set() or not self._q:
                return None
            return self._q.popleft()

    def drop(self, arrival: Arrival, reason: str) -> None:
        self.dropped.append((int(arrival.frame.index), reason))

    def stop(self, timeout: float = 0.5) -> None:
        """End the replay (the reader thread exits within `timeout` unless a frame is being decoded)."""
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)
