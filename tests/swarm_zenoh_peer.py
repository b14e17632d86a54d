"""One peer process of the Zenoh test: `python swarm_zenoh_peer.py ID PORT_BASE RUN`. Opens its session, prints
`ready`, waits for a line on stdin, broadcasts 20 hellos 50 ms apart, then prints how many it got from each peer."""

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent.parent))

from slam.swarm import messages as M  # noqa: E402
from slam.swarm.zenoh_transport import ZenohTransport  # noqa: E402


def main(robot: int, port_base: int, run: str) -> None:
    tx = ZenohTransport(robot, [0, 1, 2], run=run, port_base=port_base)
    tx.wait_for_peers(30.0)
    print("ready", flush=True)
    sys.stdin.readline()
    got: dict[int, set] = {}
    for k in range(20):
        tx.send(None, M.Hello(tick=k, n_keyframes=robot))
        time.sleep(0.05)
        for h, m in tx.poll():
            got.setdefault(h.sender, set()).add(m.tick)
    t_end = time.time() + 2.0
    while time.time() < t_end and sum(map(len, got.values())) < 40:
        time.sleep(0.05)
        for h, m in tx.poll():
            got.setdefault(h.sender, set()).add(m.tick)
    tx.close()
    print(json.dumps({str(k): len(v) for k, v in got.items()}), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3])
