"""`Transport` over Zenoh (`eclipse-zenoh`): peer-to-peer sessions (or clients of a router), one per robot process.

Each robot listens on `tcp/<host>:<port_base + id>` and connects to the other robots' endpoints (multicast
scouting off, so tests stay on loopback). Messages go to key `swarmsplat/<run>/to/<dest>` or, for a broadcast,
`swarmsplat/<run>/all`. Given `listen` / `connect` endpoints instead (a team server on one machine, its agents on
others: slam.run.team_link), a node listens and connects where told; in mode "client" it only connects, to a Zenoh
router (`zenohd`) that carries every message, and reconnects when the router comes back. The rendezvous schedule is enforced on both ends with the robot's own tick clock: a robot
does not send to a robot it is not linked with, and drops what arrives from one.

`zenoh` is imported when a transport is created, so the rest of the package works without it.
"""

from __future__ import annotations

import json
import queue
from typing import Callable

from swarmsplat.kernels.errors import InputError

from . import messages as M
from .rendezvous import Schedule
from .transport import Transport


def free_port_base(n: int, start: int = 23000) -> int | None:
    """A port base whose n ports port_base .. port_base + n - 1 are free on the loopback now (robot K listens on
    port_base + K), searched from `start` on in steps that spread concurrent callers; None if there is none."""
    import os
    import socket

    for base in range(start + os.getpid() % 500 * 13, 60000, 97):
        socks = []
        try:
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
    return None


def zenoh_available() -> bool:
    try:
        import zenoh  # noqa: F401
    except ImportError:
        return False
    return True


class ZenohTransport(Transport):
    """One robot's Zenoh session. `clock()` returns the current tick (used with `schedule` to gate links)."""

    def __init__(self, robot: int, robots: list[int], *, run: str = "default", port_base: int = 17447,
                 host: str = "127.0.0.1", schedule: Schedule | None = None, clock: Callable[[], int] | None = None,
                 codec: M.Codec | None = None, listen: list[str] | None = None, connect: list[str] | None = None,
                 block: bool = False, mode: str = "peer"):
        super().__init__(robot, codec)
        if mode not in ("peer", "client"):
            raise InputError(f"Zenoh mode {mode!r}: peer or client expected")
        try:
            import zenoh
        except ImportError:
            raise InputError("the Zenoh transport needs eclipse-zenoh: pip install eclipse-zenoh") from None
        self.robots = sorted(int(r) for r in robots)
        self.team = set(self.robots)
        self.schedule, self.clock = schedule, clock or (lambda: 0)
        self.prefix = f"swarmsplat/{run}"
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        if listen is None and connect is None:  # robot K on port_base + K, connected to every other robot
            listen = [f"tcp/{host}:{port_base + self.robot}"]
            connect = [f"tcp/{host}:{port_base + r}" for r in self.robots if r != self.robot]
        conf.insert_json5("listen/endpoints", json.dumps(list(listen or [])))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect or [])))
        try:  # peers start in any order: retry connecting quickly instead of Zenoh's slow default back-off
            conf.insert_json5("connect/retry", '{"period_init_ms": 100, "period_max_ms": 500, '
                                               '"period_increase_factor": 1.5}')
        except Exception:  # noqa: BLE001 (older releases without the key keep their default)
            pass
        # block: a full send queue waits instead of dropping the message (Zenoh's default for puts drops)
        self._put_kw = {"congestion_control": zenoh.CongestionControl.BLOCK} if block else {}
        self._q: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self.session = zenoh.open(conf)
        cb = lambda sample: self._q.put(sample.payload.to_bytes())  # noqa: E731  (runs on Zenoh's thread)
        self._subs = [self.session.declare_subscriber(f"{self.prefix}/to/{self.robot}", cb),
                      self.session.declare_subscriber(f"{self.prefix}/all", cb)]

    def wait_for_peers(self, timeout: float = 30.0) -> int:
        """Block until a session is open with every other robot (or `timeout` seconds); returns how many are."""
        import time

        t_end = time.time() + timeout
        n = 0
        while time.time() < t_end:
            n = len(list(self.session.info.peers_zid()))
            if n >= len(self.robots) - 1:
                break
            time.sleep(0.05)
        return n

    def neighbours(self) -> list[int]:
        """Robots linked now by the schedule (all of them without one); Zenoh keeps the sessions themselves."""
        return [r for r in self.robots if r != self.robot and self._linked(r)]

    def _linked(self, other: int) -> bool:
        return self.schedule is None or self.schedule.linked(self.clock(), self.robot, other)

    def send(self, dest: int | None, msg: M.Message) -> int:
        if dest is not None and not self._linked(int(dest)):
            return 0  # out of range: nothing leaves the robot
        if dest is None and not any(self._linked(r) for r in self.robots if r != self.robot):
            return 0
        return super().send(dest, msg)

    def _send_bytes(self, dest: int | None, data: bytes) -> None:
        key = f"{self.prefix}/all" if dest is None else f"{self.prefix}/to/{int(dest)}"
        self.session.put(key, data, **self._put_kw)

    def _receive_bytes(self) -> list[bytes]:
        out = []
        while True:
            try:
                data = self._q.get_nowait()
            except queue.Empty:
                return out
            try:
                sender = self.codec.peek_header(data).sender
            except M.MessageError:
                out.append(data)  # let poll() count it as rejected
                continue
            if sender not in self.team or self._linked(sender):  # poll() counts a foreign robot's message
                out.append(data)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()
