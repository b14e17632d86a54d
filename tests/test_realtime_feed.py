"""The real-time feed (slam.run.realtime.feed): frames arriving faster than the tracker takes them are dropped and
counted, never queued without bound; a reader that falls behind skips to the frame due now; each frame is prepared
on the reader's thread; the replay rate comes from the timestamps or --rate."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

# ---- the feed: bounded, every frame accounted for ----------------------------------------------------------------


@dataclass
class _Frame:
    index: int


class _Seq:
    def __getitem__(self, i):
        return _Frame(i)


class _Skips:
    def skip_frame(self, index, reason):
        raise AssertionError("nothing to skip")


@pytest.mark.parametrize("queue", [1, 3])
def test_feed_drops_and_counts_what_a_slow_tracker_cannot_take(queue):
    from swarmsplat.slam.run.realtime.feed import FrameFeed

    n = 60
    feed = FrameFeed(_Seq(), np.arange(n) / 400.0, queue=queue, skipper=_Skips())  # 400 Hz
    feed.start()
    taken, longest = [], 0
    while (a := feed.take()) is not None:
        with feed._cv:
            longest = max(longest, len(feed._q) + 1)  # what waited, this frame included
        taken.append(a.frame.index)
        time.sleep(0.02)  # a tracker 8x slower than the sensor
    dropped = [i for i, _ in feed.dropped]
    late = [i for i, why in feed.dropped if why == "reader_late"]  # a busy machine may hold the reader up
    assert longest <= queue  # bounded
    assert sorted(taken + dropped) == list(range(n)) and feed.arrived == n - len(late)  # each taken or dropped
    assert {r for _, r in feed.dropped} <= {"queue_full", "reader_late"} and len(dropped) > n // 2
    assert taken == sorted(taken)  # in order, the oldest waiting frame first


def test_a_reader_that_falls_behind_skips_to_the_frame_due_now():
    """Decoding a frame takes 2.5 intervals: the reader skips the frames that are overdue before it reads them
    (reader_late), so its lag stays under one read, not growing frame by frame."""
    from swarmsplat.slam.run.realtime.feed import FrameFeed

    class Slow(_Seq):
        def __getitem__(self, i):
            time.sleep(0.025)
            return _Frame(i)

    n = 40
    feed = FrameFeed(Slow(), np.arange(n) / 100.0, queue=n, skipper=_Skips())  # 100 Hz
    feed.start()
    while feed.take() is not None:
        pass
    late = [i for i, why in feed.dropped if why == "reader_late"]
    assert len(late) > n // 2 and feed.arrived + len(late) == n
    assert max(feed.late) < 0.1  # without skipping: 39 frames x 15 ms behind = 0.6 s


def test_feed_prepares_each_frame_on_its_reader_thread():
    """`prepare` runs before a frame is due, on the reader's thread; a frame it refuses (None) does not arrive."""
    from swarmsplat.slam.run.realtime.feed import FrameFeed

    threads = set()

    def prepare(f):
        threads.add(threading.current_thread().name)
        return None if f.index % 3 == 1 else ("ready", f.index)

    feed = FrameFeed(_Seq(), np.arange(9) / 200.0, queue=9, skipper=_Skips(), prepare=prepare)
    feed.start()
    got = []
    while (a := feed.take()) is not None:
        got.append(a.prepared)
    assert got == [("ready", i) for i in range(9) if i % 3 != 1] and threads == {"realtime-feed"}


def test_rate_from_timestamps_or_flag():
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.run.realtime.feed import arrival_offsets

    t, dt = arrival_offsets(np.array([10.0, 10.1, 10.2, 10.35]), 4, 0.0)
    np.testing.assert_allclose(t, [0, 0.1, 0.2, 0.35], atol=1e-12)
    assert dt == pytest.approx(0.1)  # the median step, not the mean (0.1167)
    t, dt = arrival_offsets(np.zeros(4), 3, 20.0)
    np.testing.assert_allclose(t, [0, 0.05, 0.1], atol=1e-12)
    assert dt == 0.05
    with pytest.raises(InputError, match="--rate"):
        arrival_offsets(np.zeros(4), 4, 0.0)  # no rate of its own
