"""The real-time scheduler's `stale` rule (slam.run.realtime.schedule) on a simulated stream with a fake clock: a
sensor at a fixed rate, a queue of one frame, a tracker whose cost per frame is given and a constant hand-off delay
(the reader's lateness and the thread's wake-up), driven through the calls the run makes (take, posed, free)."""

from __future__ import annotations

import itertools

import pytest

from swarmsplat.slam.run.realtime.schedule import Scheduler

HZ30 = 1 / 30


def _replay(sched: Scheduler, cost, *, n: int, interval: float = HZ30, handoff=lambda i: 2e-4):
    """Frames 0..n-1 due at i * interval; `cost(i)` s from taking frame i to its pose, `handoff(i)` s from the
    later of its arrival and the tracker becoming free to the tracker taking it. Returns (latency per tracked
    frame {index: s}, [(index, reason)] of the dropped frames in order)."""
    latency, dropped = {}, []
    free, i = 0.0, 0
    while i < n:
        newest = max(i, min(n - 1, int(free / interval)))  # the last frame to have arrived by `free`, if any
        dropped += [(j, "queue_full") for j in range(i, newest)]  # pushed out of the queue of one by a newer one
        i = newest
        due = i * interval
        now = max(free, due) + handoff(i)
        why = sched.take(now, due)
        if why is None:
            posed = now + cost(i)
            sched.posed(now, posed)
            latency[i] = posed - due
            free = posed
        else:
            dropped.append((i, why))
            free = now
        sched.free(free)
        i += 1
    return latency, dropped


def _longest_run(indices: list[int]) -> int:
    """The longest run of consecutive frame indices."""
    runs = [len(list(g)) for _, g in itertools.groupby(enumerate(sorted(indices)), lambda p: p[1] - p[0])]
    return max(runs, default=0)


def test_a_tracker_just_inside_the_budget_keeps_tracking():
    """The case that once dropped every frame from frame 102 on: the pose time grows to within the hand-off delay
    of the budget (26 ms here). The rule used to compare a waiting frame with a next frame taken with no wait at
    all, and measured nothing while it dropped, so from then on every frame was stale. Now a fresh frame is
    expected to wait what fresh frames waited, and a frame whose pose cannot be on time either way is tracked."""
    def cost(i):
        return 0.020 if i < 100 else 0.0259

    latency, dropped = _replay(Scheduler(0.026), cost, n=211)
    assert dropped == [] and len(latency) == 211
    assert max(latency[i] for i in range(100, 211)) == pytest.approx(0.0261)


def test_a_run_of_stale_drops_ends_by_itself():
    """From frame 100 on every frame waits 0.3 ms longer (a reader fallen behind), which puts each pose just past
    the budget: the first of them are dropped, each raises the expected hand-off, and once the estimate has them
    (at most its window of 20 frames later) every frame is tracked again, late by 0.2 ms."""
    def handoff(i):
        return 1e-4 if i < 100 else 4e-4

    latency, dropped = _replay(Scheduler(0.026, window=20), lambda i: 0.0258, n=300, handoff=handoff)
    stale = [i for i, why in dropped if why == "stale"]
    assert dropped == [(i, "stale") for i in stale] and stale[0] == 100
    assert len(stale) == _longest_run(stale) <= 20
    assert all(i in latency for i in range(stale[-1] + 1, 300))


def test_a_frame_that_waited_behind_a_slow_step_is_dropped_for_the_next():
    """One 80 ms step at 30 Hz with a 33.3 ms budget: the frame that arrived during it is pushed out by a newer one
    (queue_full), the newer one has waited too long for its pose to be on time (stale), and the one after is
    posed in time again."""
    def cost(i):
        return 0.080 if i == 50 else 0.020

    latency, dropped = _replay(Scheduler(HZ30), cost, n=100)
    assert dropped == [(51, "queue_full"), (52, "stale")]
    assert max(v for i, v in latency.items() if i != 50) < HZ30
    assert latency[53] == pytest.approx(0.0202)


def test_nothing_is_stale_before_the_first_pose_nor_when_no_frame_can_be_on_time():
    """No estimate before the first pose; a tracker slower than the budget tracks every frame it takes, late (the
    queue of one bounds the wait)."""
    s = Scheduler(HZ30)
    assert s.take(1.0, 0.0) is None  # waited 1 s, but nothing is known yet
    latency, dropped = _replay(Scheduler(HZ30), lambda i: 0.050, n=60)
    assert {why for _, why in dropped} == {"queue_full"} and len(latency) == 60 - len(dropped) > 30
