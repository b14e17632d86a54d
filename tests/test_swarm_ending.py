"""The end of a mission is a protocol (slam.flocc.swarm.ending): after the schedule's last tick robots go on until
every candidate is verified and every robot of the group holds the final estimate; a robot that vanished holds
the others only until the timeout, and is reported. In-process, with the exact stand-in front-end."""

import numpy as np
from swarm_fakes import scenario
from test_swarm_runtime import N_KF, make_node, run

from swarmsplat.slam.flocc.swarm.ending import MissionEnd
from swarmsplat.slam.flocc.swarm.rendezvous import Schedule, Window
from swarmsplat.slam.flocc.swarm.transport import Faults, InProcessNetwork


def late_schedule(ticks=16):
    """Pairs meet while recording; everyone meets only at the very last tick: nothing can be exchanged in time."""
    return Schedule(ticks, 1, 0.1, [Window(3, 6, frozenset({0, 1})), Window(7, 10, frozenset({1, 2})),
                                    Window(ticks - 1, ticks, frozenset({0, 1, 2}))])


def run_to_end(sched, faults=None, on_tick=None, timeout_s=3.0, solver="lm"):
    """`test_swarm_runtime.run`, then the end protocol until every robot stops (at most timeout_s seconds)."""
    data = scenario(3, N_KF)
    net = InProcessNetwork(range(3), sched, faults)
    nodes = [make_node(r, net, solver) for r in range(3)]
    for n in nodes:
        n.cfg.end_timeout = timeout_s
    ends = [MissionEnd.on_schedule(n, sched, range(3)) for n in nodes]
    stopped, last = set(), {}
    for tick in range(sched.ticks + ends[0].timeout_ticks + 1):
        if tick >= sched.ticks and {0, 1, 2} <= stopped | net.killed:
            break
        if on_tick:
            on_tick(tick, net, nodes)
        net.advance(tick)
        for r, node in enumerate(nodes):
            if r in net.killed or r in stopped:
                continue
            while len(node.images) < min(N_KF, sched.frames_at(tick)):
                k = len(node.images)
                node.add_keyframe(data[r][0][k], data[r][1][k], float(k))
            node.step(tick)
            if tick >= sched.ticks - 1 and ends[r].step(tick):
                stopped.add(r)
                last[r] = tick
    return nodes, ends, last


def _same_final(nodes, ref, robots=(0, 1, 2)):
    for r in robots:
        assert nodes[r].estimate is not None and nodes[r].estimate.robots.tolist() == ref[r].estimate.robots.tolist()
        np.testing.assert_allclose(nodes[r].estimate.poses, ref[r].estimate.poses, atol=1e-9)


def test_schedule_end_alone_leaves_the_team_unmerged():
    """What the protocol fixes: with the schedule's end as the mission's end the robots hold different estimates."""
    nodes, _ = run(late_schedule())
    stamps = [n.estimate.stamp if n.estimate is not None else None for n in nodes]
    assert stamps[0] != stamps[2] or stamps[0] is None


def test_end_protocol_reaches_the_long_run_result():
    ref, _ = run()  # everyone in range for 28 ticks after the pairs' meetings
    nodes, ends, last = run_to_end(late_schedule())
    _same_final(nodes, ref)
    assert len({tuple(n.estimate.stamp) for n in nodes}) == 1  # one final estimate, held by everyone
    assert all(e.report()["status"] == "complete" and e.report()["missing"] == [] for e in ends)
    assert max(last.values()) < late_schedule().ticks + 20  # well before the timeout (30 ticks)


def test_end_protocol_under_faults():
    ref, _ = run()
    nodes, ends, _ = run_to_end(late_schedule(), Faults(drop=0.2, duplicate=0.3, delay=(0, 2), reorder=True, seed=7),
                                timeout_s=6.0)
    _same_final(nodes, ref)
    assert all(e.status == "complete" for e in ends)


def test_vanished_robot_is_reported_and_the_others_finish():
    sched = late_schedule()

    def hook(tick, net, nodes):
        if tick == sched.ticks + 1:  # robot 2 vanishes during the end protocol
            net.kill(2)

    nodes, ends, last = run_to_end(sched, on_tick=hook, timeout_s=2.0)
    for r in (0, 1):
        rep = ends[r].report()
        assert rep["status"] == "timeout" and rep["missing"] == [2], rep
        assert last[r] == sched.ticks - 1 + ends[r].timeout_ticks  # bounded by the timeout
    assert nodes[0].estimate.stamp == nodes[1].estimate.stamp
    np.testing.assert_array_equal(nodes[0].estimate.poses, nodes[1].estimate.poses)
    assert np.all(np.isfinite(nodes[0].estimate.poses))


def test_robot_alone_at_the_end_stops_at_once():
    sched = Schedule(14, 1, 0.1, [Window(3, 10, frozenset({0, 1, 2}))])
    nodes, ends, last = run_to_end(sched)
    assert all(e.report() == {"status": "complete", "ticks": 1, "group": [], "missing": []} for e in ends)
    assert set(last.values()) == {sched.ticks - 1}
