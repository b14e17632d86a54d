"""One robot process of the Zenoh tests: `python swarm_zenoh_robot.py ID PORT_BASE OUT.npz RUN [END_TIMEOUT_S]
[VANISH_AT_TICK]`. Prints `ready` once its peers are connected, reads the common start time (epoch seconds of
tick 0) from stdin, runs the node of `test_swarm_ending`'s late-meeting scenario on wall-clock ticks with the
schedule enforced, then the end protocol, and saves its final estimate and how the protocol ended. With
VANISH_AT_TICK it exits at that tick without a word (a robot that vanished)."""

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent.parent))

from swarm_fakes import CAMERA, FakeRecognizer, FakeRegistrar, scenario  # noqa: E402
from test_swarm_ending import late_schedule  # noqa: E402
from test_swarm_runtime import N_KF  # noqa: E402

from swarmsplat.slam.flocc.swarm.clocked import TickClock, run_clocked  # noqa: E402
from swarmsplat.slam.flocc.swarm.ending import MissionEnd  # noqa: E402
from swarmsplat.slam.flocc.swarm.node import NodeConfig, RobotNode  # noqa: E402
from swarmsplat.slam.flocc.swarm.optimiser import SolveConfig, warm_up  # noqa: E402
from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport  # noqa: E402


def main(robot: int, port_base: int, out: str, run: str, end_timeout: float = 20.0, vanish_at: int = -1) -> None:
    sched = late_schedule()
    data = scenario(3, N_KF)[robot]
    clock = TickClock()
    tx = ZenohTransport(robot, [0, 1, 2], run=run, port_base=port_base, schedule=sched, clock=clock)
    node = RobotNode(robot, CAMERA, tx, FakeRecognizer(), FakeRegistrar(),
                     NodeConfig(solve=SolveConfig("is", "lm"), end_timeout=end_timeout))
    end = MissionEnd.on_schedule(node, sched, range(3))

    def step(tick):
        if tick == vanish_at:
            os._exit(0)
        while len(node.images) < min(N_KF, sched.frames_at(tick)):
            k = len(node.images)
            node.add_keyframe(data[0][k], data[1][k], float(k))
        node.step(tick)
        return tick >= sched.ticks - 1 and end.step(tick)

    warm_up()
    tx.wait_for_peers(30.0)
    print("ready", flush=True)
    start = float(sys.stdin.readline())
    late = time.time() - start
    try:
        skipped = run_clocked(step, sched.ticks + end.timeout_ticks, start, sched.tick_seconds, clock)
    finally:
        tx.close()
    e = node.estimate
    print(f"robot {robot}: started {late:+.2f} s after tick 0, skipped {skipped} ticks, ended {end.report()} "
          f"{time.time() - start:.1f} s after tick 0; sent {dict(tx.stats.sent_count)} "
          f"received {dict(tx.stats.recv_count)}", file=sys.stderr)
    np.savez(out, poses=e.poses if e else np.zeros((0, 4, 4)), robots=e.robots if e else np.zeros(0),
             stamp=e.stamp if e else [], sent=tx.stats.to_dict()["sent_total"], end=json.dumps(end.report()),
             seconds=time.time() - start)


if __name__ == "__main__":
    a = sys.argv[1:]
    main(int(a[0]), int(a[1]), a[2], a[3], float(a[4]) if len(a) > 4 else 20.0, int(a[5]) if len(a) > 5 else -1)
