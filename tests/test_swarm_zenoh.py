"""Zenoh transport on loopback: delivery, rendezvous gating on both ends, rejection of foreign bytes; three robot
processes (peer-to-peer, no broker) reach the in-process run's estimates. Skipped without eclipse-zenoh."""

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from swarmsplat.slam.flocc.swarm import messages as M
from swarmsplat.slam.flocc.swarm.rendezvous import Schedule, Window
from swarmsplat.slam.flocc.swarm.zenoh_transport import zenoh_available

pytestmark = pytest.mark.skipif(not zenoh_available(), reason="eclipse-zenoh is not installed")


def _free_port_base(n=3):
    for base in range(23000 + os.getpid() % 500 * 13, 60000, 97):
        try:
            socks = []
            for r in range(n):
                s = socket.socket()
                socks.append(s)
                s.bind(("127.0.0.1", base + r))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    pytest.skip("no free loopback ports")


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


def test_robot_processes_match_in_process(tmp_path):
    """Three robot nodes, one process each, on 0.1 s ticks of the runtime tests' schedule: the final estimates
    equal the in-process run's (the same graphs reach the optimiser, whatever the timing)."""
    from test_swarm_runtime import run

    here = Path(__file__).parent
    base = _free_port_base(3)
    procs = [subprocess.Popen([sys.executable, str(here / "swarm_zenoh_robot.py"), str(r), str(base),
                               str(tmp_path / f"r{r}.npz"), f"r{os.getpid()}"],
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
    ref, _ = run()
    for r in range(3):
        got = np.load(tmp_path / f"r{r}.npz")
        assert got["robots"].tolist() == ref[r].estimate.robots.tolist(), logs
        np.testing.assert_allclose(got["poses"], ref[r].estimate.poses, atol=1e-6)
