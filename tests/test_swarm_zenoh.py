"""Zenoh transport on loopback: delivery, rendezvous gating on both ends, rejection of foreign bytes; three robot
processes (peer-to-peer, no broker) reach the in-process run's estimates through the end protocol, and finish
without a robot that vanished. Skipped without eclipse-zenoh."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from swarmsplat.slam.flocc.swarm import messages as M
from swarmsplat.slam.flocc.swarm.rendezvous import Schedule, Window
from swarmsplat.slam.flocc.swarm.zenoh_transport import free_port_base, zenoh_available

pytestmark = pytest.mark.skipif(not zenoh_available(), reason="eclipse-zenoh is not installed")


def _free_port_base(n=3):
    base = free_port_base(n)
    if base is None:
        pytest.skip("no free loopback ports")
    return base


def _drain(tx, want, timeout=5.0):
    out, t_end = [], time.time() + timeout
    while len(out) < want and time.time() < t_end:
        out += tx.poll()
        time.sleep(0.02)
    return out


def test_delivery_and_schedule_gating():
    from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport

    base = _free_port_base(2)
    sched = Schedule(10, 1, 0.1, [Window(2, 5, frozenset({0, 1}))])
    tick = {"t": 3}
    a = ZenohTransport(0, [0, 1], run=f"g{os.getpid()}", port_base=base, schedule=sched, clock=lambda: tick["t"])
    b = ZenohTransport(1, [0, 1], run=f"g{os.getpid()}", port_base=base, schedule=sched, clock=lambda: tick["t"])
    try:
        assert a.wait_for_peers(20) == 1
        time.sleep(0.5)  # subscriptions propagate
        assert a.send(1, M.Hello(tick=1)) > 0 and a.send(None, M.Hello(tick=2)) > 0
        got = _drain(b, 2)
        assert sorted(m.tick for _, m in got) == [1, 2] and all(h.sender == 0 for h, _ in got)
        assert a.neighbours() == [1]
        tick["t"] = 7  # out of range: nothing leaves a, nothing from a is accepted by b
        assert a.neighbours() == []
        assert a.send(1, M.Hello(tick=3)) == 0 and a.send(None, M.Hello(tick=4)) == 0
        tick["t"] = 3
        b.send(0, M.Hello(tick=5))
        tick["t"] = 7
        assert _drain(a, 1, timeout=1.0) == []
        tick["t"] = 3
        a.session.put(f"{a.prefix}/to/1", b"not a swarmsplat message")
        assert _drain(b, 1, timeout=1.0) == [] and b.stats.rejected == 1
    finally:
        a.close()
        b.close()


def _robots(tmp_path, extra=((), (), ())):
    """Run the three robot processes of `swarm_zenoh_robot.py` (extra arguments per robot) from a common tick 0;
    returns their saved results and their stderr."""
    here = Path(__file__).parent
    base = _free_port_base(3)
    procs = [subprocess.Popen([sys.executable, str(here / "swarm_zenoh_robot.py"), str(r), str(base),
                               str(tmp_path / f"r{r}.npz"), f"r{os.getpid()}", *map(str, extra[r])],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for r in range(3)]
    try:
        for p in procs:  # a barrier: every robot's peers are connected before the common tick 0 is chosen
            assert p.stdout.readline().strip() == "ready"
        start = time.time() + 1.0
        for p in procs:
            p.stdin.write(f"{start}\n")
            p.stdin.flush()
        logs = []
        for p in procs:
            out, err = p.communicate(timeout=90)  # read the pipes so a chatty process never blocks
            logs.append(err[-1500:])
            assert p.returncode == 0, err[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    return {r: dict(np.load(tmp_path / f"r{r}.npz")) for r in range(3) if (tmp_path / f"r{r}.npz").exists()}, logs


def test_robot_processes_match_in_process(tmp_path):
    """Three robot nodes, one process each, on 0.1 s ticks of a schedule that brings everyone together only at
    its last tick: nothing can be exchanged in time, so the team merges in the end protocol, and every robot ends
    with the estimate of the in-process run that had 28 ticks together (the same graphs reach the optimiser,
    whatever the timing)."""
    from test_swarm_runtime import run

    got, logs = _robots(tmp_path)
    ref, _ = run()
    for r in range(3):
        assert json.loads(str(got[r]["end"]))["status"] == "complete", logs
        assert got[r]["robots"].tolist() == ref[r].estimate.robots.tolist(), logs
        np.testing.assert_allclose(got[r]["poses"], ref[r].estimate.poses, atol=1e-6)
    assert got[0]["stamp"].tolist() == got[1]["stamp"].tolist() == got[2]["stamp"].tolist(), logs


def test_vanished_robot_process(tmp_path):
    """Robot 2 exits without a word before the team meets: robots 0 and 1 finish when the end protocol times
    out (3 s), report robot 2 missing, and hold the same estimate of the two of them."""
    got, logs = _robots(tmp_path, ((3.0,), (3.0,), (3.0, 12)))
    assert set(got) == {0, 1}
    for r in (0, 1):
        end = json.loads(str(got[r]["end"]))
        assert end["status"] == "timeout" and end["missing"] == [2], logs
        assert float(got[r]["seconds"]) < 1.6 + 3.0 + 3.0, logs  # the schedule, the timeout, some slack
    assert got[0]["robots"].tolist() == got[1]["robots"].tolist() == [0, 1], logs
    np.testing.assert_array_equal(got[0]["poses"], got[1]["poses"])


LATE = "ticks: 16\nframes_per_tick: 2\ntick_seconds: 0.1\nwindows:\n  - {start: 15, end: 16, robots: [0, 1, 2]}\n"


def test_swarm_processes_give_the_in_process_result(tmp_path):
    """`swarm --processes` on a small generated team, three times, against the in-process run on the same
    schedule. The robots meet only at the schedule's last tick (0.1 s ticks), so descriptors, encodings, loops,
    graphs and the final estimate all travel in the end protocol: every run must end with the in-process loops
    and trajectories, every robot holding the same final estimate."""
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.run.swarm import run_swarm
    from swarmsplat.slam.run.swarm_processes import launch

    data = tmp_path / "data"
    assert main(["generate", "--out", str(data), "--preset", "tiny", "--agents", "3", "--frames", "30", "--mono",
                 "--quiet"]) == 0
    (tmp_path / "late.yaml").write_text(LATE)
    opts = {"stride": 2, "schedule": str(tmp_path / "late.yaml")}
    ref = run_swarm(data, tmp_path / "inproc", progress=False, **opts)
    loops = ref["loop_closures"]["count"]
    assert loops > 10 and ref["ate"]["merged_rmse"] < 0.8 * ref["odometry_only_ate"]["merged_rmse"]
    assert all(e["status"] == "complete" for e in ref["end"].values())
    for k in range(3):
        out = tmp_path / f"zenoh{k}"
        m = launch(data, out, port_base=_free_port_base(3), **opts)
        assert m["loop_closures"]["count"] == loops, (k, m["end"])
        assert all(e["status"] == "complete" for e in m["end"].values()), (k, m["end"])
        assert len({tuple(s) for s in m["estimate_stamp"].values()}) == 1, (k, m["estimate_stamp"])
        assert abs(m["ate"]["merged_rmse"] - ref["ate"]["merged_rmse"]) <= 0.1 * ref["ate"]["merged_rmse"], k
        for name in ("agent_0", "agent_1", "agent_2"):
            np.testing.assert_allclose(np.loadtxt(out / f"{name}.txt"), np.loadtxt(tmp_path / "inproc" / f"{name}.txt"),
                                       atol=1e-6)


def test_swarm_processes_solve_distributed(tmp_path):
    """`swarm --processes --solver distributed`: every robot process solves its own part over Zenoh (the code of the
    in-process run), no graph gathered; the team ends at the centralised optimum of its final graph, with the
    in-process run's loops."""
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.run.swarm import run_swarm
    from swarmsplat.slam.run.swarm_processes import launch

    data = tmp_path / "data"
    assert main(["generate", "--out", str(data), "--preset", "tiny", "--agents", "3", "--frames", "30", "--mono",
                 "--quiet"]) == 0
    (tmp_path / "late.yaml").write_text(LATE)
    opts = {"stride": 2, "schedule": str(tmp_path / "late.yaml"), "solver": "distributed"}
    ref = run_swarm(data, tmp_path / "inproc", progress=False, **opts)
    m = launch(data, tmp_path / "zenoh", port_base=_free_port_base(3), **opts)
    for run in (ref, m):
        assert all(e["status"] == "complete" for e in run["end"].values()), run["end"]
        assert run["distributed"]["ratio"] <= 1.001, run["distributed"]
        assert all("GraphSubmission" not in b["sent_bytes"] for b in run["bytes"].values())
    assert m["loop_closures"]["count"] == ref["loop_closures"]["count"]
    assert abs(m["ate"]["merged_rmse"] - ref["ate"]["merged_rmse"]) <= 0.02 * ref["ate"]["merged_rmse"]
