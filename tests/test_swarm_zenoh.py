"""Zenoh transport on loopback: delivery, rendezvous gating on both ends, rejection of foreign bytes, and three
peer processes exchanging messages without a broker. Skipped without eclipse-zenoh."""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slam.swarm import messages as M
from slam.swarm.rendezvous import Schedule, Window
from slam.swarm.zenoh_transport import zenoh_available

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
    from slam.swarm.zenoh_transport import ZenohTransport

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
        tick["t"] = 7  # out of range: nothing leaves a, nothing from a is accepted by b
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


def test_three_peer_processes_without_broker():
    here = Path(__file__).parent
    base = _free_port_base(3)
    procs = [subprocess.Popen([sys.executable, str(here / "swarm_zenoh_peer.py"), str(r), str(base), f"p{os.getpid()}"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for r in range(3)]
    try:
        for p in procs:
            assert p.stdout.readline().strip() == "ready"
        time.sleep(0.5)
        for p in procs:
            p.stdin.write("go\n")
            p.stdin.flush()
        results = []
        for p in procs:
            out, err = p.communicate(timeout=60)
            assert p.returncode == 0, err[-2000:]
            results.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for r, got in enumerate(results):
        assert set(got) == {str(o) for o in range(3) if o != r}
        assert all(n >= 15 for n in got.values()), got  # hellos sent while every peer was listening
