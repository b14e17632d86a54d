"""The end of a mission: a protocol, not the schedule's last tick. Robots go on exchanging until no loop candidate
is left to verify and every robot of their group holds the final estimate, bounded by a timeout.

When the schedule ends, work may still be under way: over Zenoh a robot busy registering skips ticks, and
descriptors, encodings, loops, graphs and the last estimate may still be in flight. From the schedule's last tick
on, a robot's group is fixed: the robots it is linked with at that tick (those links hold while the protocol runs,
`Schedule.linked`). Each tick, after its usual step, a robot
    1. works out whether it is *ready*: no encoding it asked for is missing (every candidate is registered), and
       with every robot of its group in range, descriptors are held both ways and the loop sets agree;
    2. broadcasts `Finish`: ready, its graph version and the stamp of the estimate it holds;
    3. as the group's optimiser (lowest id in range): once every robot of the group is ready, its estimate covers
       every robot's latest graph and every robot reports holding it, announces the end (`Finish.end` = that
       stamp); it stops once every robot has echoed it, or `resend` ticks later;
    4. as another robot: stops once the optimiser has announced the end of the estimate it holds, echoing it.
A robot of the group that never confirms (vanished or cut off) holds the others until the timeout; they then stop
with what they hold, and `report()` names it.

With the distributed solver (`swarm.solver: distributed`) there is no optimiser and no final estimate: a robot is
ready when, besides the above, its part is built on its final graph and settled (its last steps and its
neighbours' were still, distributed.py), and it stops once every robot of its group has reported ready.
"""

from __future__ import annotations

import math

from . import messages as M
from .election import elect
from .node import RobotNode, stamp_of


class MissionEnd:
    """The end protocol of one robot (module docstring). `group`: the robots linked with it at the schedule's
    last tick; `timeout_ticks`: how many ticks the protocol may run before the robot stops anyway."""

    def __init__(self, node: RobotNode, group, timeout_ticks: int):
        self.node = node
        self.group = sorted({int(r) for r in group} - {node.id})
        self.timeout_ticks = int(timeout_ticks)
        self.first: int | None = None  # first tick of the protocol
        self.last: int | None = None
        self.announced: tuple[list[int], int] | None = None  # as optimiser: (final stamp, tick announced)
        self.status = "running"  # then "complete" or "timeout"

    @classmethod
    def on_schedule(cls, node: RobotNode, schedule, robots) -> "MissionEnd":
        """The protocol of `node` at the end of `schedule`: its group is the robots (of `robots`) linked with it
        at the last tick; the timeout is the node's `end_timeout` seconds in ticks of the schedule."""
        group = schedule.neighbours(schedule.ticks - 1, node.id, robots)
        return cls(node, group, math.ceil(node.cfg.end_timeout / schedule.tick_seconds))

    # ------------------------------------------------------------------------------------------ state
    def _in_range(self) -> list[int]:
        return [r for r in self.node.neighbours() if r in self.group]

    def ready(self) -> bool:
        """No candidate left to verify, descriptors held both ways and loop sets equal with each robot in range."""
        n = self.node
        if n._pending:
            return False
        have = n._have_desc()
        for p in self._in_range():
            h = n.hello.get(p)
            if h is None or int(h.have_desc.get(str(n.id), 0)) < len(n.own_desc) \
                    or have.get(str(p), 0) < h.n_keyframes \
                    or int(h.loops_with.get(str(n.id), 0)) != n._loops_digest(p):
                return False
        return True

    def _final(self, ready: bool) -> bool:
        """As optimiser: every robot of the group ready and holding this robot's estimate, which covers every
        robot's latest graph."""
        n, fin = self.node, self.node.finish
        if not ready or n.estimate is None or any(r not in fin for r in self.group):
            return False
        versions = {str(r): list(fin[r].graph_version) for r in self.group}
        versions[str(n.id)] = n.graph_version()
        stamp = stamp_of(n.estimate)
        return n.estimate.basis == versions and all(fin[r].ready and list(fin[r].estimate_stamp) == stamp
                                                    for r in self.group)

    # ------------------------------------------------------------------------------------------ the tick
    def step(self, tick: int) -> bool:
        """One tick of the protocol, after `node.step(tick)`. True once this robot may stop."""
        n = self.node
        self.first = tick if self.first is None else self.first
        self.last = tick
        if not self.group:
            return self._stop("complete")
        if n.dist is not None:
            return self._step_distributed(tick)
        ready = self.ready()
        stamp = stamp_of(n.estimate)
        end: list[int] = []
        stop = False
        if elect(n.id, self._in_range()) == n.id:
            if self.announced and (not ready or self.announced[0] != stamp):
                self.announced = None  # something changed after all: the estimate announced is not the last
            if self.announced is None and self._final(ready):
                self.announced = (stamp, tick)
            if self.announced:
                end = stamp
                echoed = all(r in n.finish and list(n.finish[r].end) == stamp for r in self.group)
                stop = echoed or tick - self.announced[1] >= n.cfg.resend
        else:
            f = n.finish.get(elect(n.id, self._in_range()))
            if ready and f is not None and f.end and list(f.end) == stamp:
                end, stop = stamp, True
        n.tx.send(None, M.Finish(tick=tick, ready=int(ready), graph_version=n.graph_version(),
                                 estimate_stamp=stamp, end=end))
        if stop:
            return self._stop("complete")
        if tick - self.first >= self.timeout_ticks:
            return self._stop("timeout")
        return False

    def _step_distributed(self, tick: int) -> bool:
        n = self.node
        ready = self.ready() and n.dist.settled(self._in_range())
        n.tx.send(None, M.Finish(tick=tick, ready=int(ready), graph_version=n.graph_version(),
                                 estimate_stamp=[n.dist.stamp], end=[]))
        if ready and all(r in n.finish and n.finish[r].ready for r in self.group):
            return self._stop("complete")
        if tick - self.first >= self.timeout_ticks:
            return self._stop("timeout")
        return False

    def _stop(self, status: str) -> bool:
        self.status = status
        return True

    def report(self) -> dict:
        """status ("running", "complete" or "timeout"), ticks the protocol ran, the group, and `missing`: the
        robots of the group not heard from in the last `neighbour_timeout` ticks (vanished or cut off)."""
        ticks = 0 if self.first is None else self.last - self.first + 1
        return {"status": self.status, "ticks": ticks, "group": self.group,
                "missing": [r for r in self.group if r not in self.node.neighbours()]}
