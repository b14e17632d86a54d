"""One robot process of the Zenoh test: `python swarm_zenoh_robot.py ID PORT_BASE OUT.npz RUN`. Prints `ready`
once its peers are connected, reads the common start time (epoch seconds of tick 0) from stdin, runs the node of
`test_swarm_runtime`'s scenario on wall-clock ticks with the schedule enforced, and saves its final estimate."""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent.parent))

from swarm_fakes import CAMERA, FakeRecognizer, FakeRegistrar, scenario  # noqa: E402
from test_swarm_runtime import N_KF, schedule  # noqa: E402

from swarmsplat.slam.flocc.swarm.clocked import TickClock, run_clocked  # noqa: E402
from swarmsplat.slam.flocc.swarm.node import NodeConfig, RobotNode  # noqa: E402
from swarmsplat.slam.flocc.swarm.optimiser import SolveConfig, warm_up  # noqa: E402
from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport  # noqa: E402


def main(robot: int, port_base: int, out: str, run: str) -> None:
    sched = schedule(40)
    data = scenario(3, N_KF)[robot]
    clock = TickClock()
    tx = ZenohTransport(robot, [0, 1, 2], run=run, port_base=port_base, schedule=sched, clock=clock)
    node = RobotNode(robot, CAMERA, tx, FakeRecognizer(), FakeRegistrar(), NodeConfig(solve=SolveConfig("is", "lm")))

    def step(tick):
        while len(node.images) < min(N_KF, sched.frames_at(tick)):
            k = len(node.images)
            node.add_keyframe(data[0][k], data[1][k], float(k))
        node.step(tick)

    warm_up()
    tx.wait_for_peers(30.0)
    print("ready", flush=True)
    start = float(sys.stdin.readline())
    late = time.time() - start
    try:
        skipped = run_clocked(step, sched.ticks, start, sched.tick_seconds, clock)
    finally:
        tx.close()
    e = node.estimate
    print(f"robot {robot}: started {late:+.2f} s after tick 0, skipped {skipped} ticks; sent {dict(tx.stats.sent_count)} "
          f"received {dict(tx.stats.recv_count)}", file=sys.stderr)
    np.savez(out, poses=e.poses if e else np.zeros((0, 4, 4)), robots=e.robots if e else np.zeros(0),
             sent=tx.stats.to_dict()["sent_total"])


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4])
