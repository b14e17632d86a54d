"""Agent ids by name: `swarmsplat agent SOURCE --name NAME --server ENDPOINT` without `--id` asks the server which
index NAME has in the team, and the server answers over a Zenoh query (key `swarmsplat/<run>/register`).

The server's answer is stable: a name it was started with (the sequences of its `--dataset`) keeps that
sequence's index, so agents named as the dataset's sequences get the in-process team's order; another name takes
the lowest free index, in the order the agents ask; a name asked again (an agent restarted, a server restarted on
its journal) gets the index it had. A full team answers with the names it holds.
"""

from __future__ import annotations

import json
import threading
import time

from swarmsplat.kernels.errors import InputError, SwarmsplatError


class Registry:
    """Indices 0 .. N-1 by name. `fixed`: names bound to their index from the start (the dataset's sequences);
    `taken`: names already joined (a server restarted on its journal)."""

    def __init__(self, n: int, *, fixed: list[str] | None = None, taken: dict[str, int] | None = None):
        self.n = int(n)
        self.fixed = {name: k for k, name in enumerate(fixed or [])}
        self.names: dict[str, int] = dict(taken or {})
        self._lock = threading.Lock()

    def assign(self, name: str) -> int:
        """NAME's index; InputError when the team is full or the name is empty."""
        if not name:
            raise InputError("an agent registers with a name")
        with self._lock:
            if name in self.names:
                return self.names[name]
            k = self.fixed.get(name)
            if k is None or k in self.names.values():
                used = set(self.names.values()) | {i for n, i in self.fixed.items() if n not in self.names}
                free = [i for i in range(self.n) if i not in used]
                if not free and k is None and self.fixed:
                    raise InputError(f"{name} is none of the server's dataset's agents "
                                     f"({', '.join(self.fixed)}): name one of them, or give --id")
                if not free:
                    raise InputError(f"the team is full: {self.n} agents ({', '.join(sorted(self.names))})")
                k = free[0]
            self.names[name] = k
            return k


def serve_registry(session, run: str, registry: Registry):
    """Answer `register` queries on `session` (the server's Zenoh session) from `registry`; returns the
    queryable (undeclare it to stop)."""

    def answer(query) -> None:
        name = query.payload.to_bytes().decode(errors="replace") if query.payload is not None else ""
        try:
            reply = {"index": registry.assign(name)}
        except InputError as e:
            reply = {"error": str(e)}
        query.reply(query.key_expr, json.dumps(reply).encode())

    return session.declare_queryable(f"swarmsplat/{run}/register", answer)


def ask_index(name: str, *, connect: list[str], listen: list[str] | None = None, run: str = "team",
              timeout: float = 30.0, say=None) -> int:
    """Ask the server at `connect` for NAME's index; SwarmsplatError when no server answers within `timeout` s
    or the server refuses (a full team)."""
    from swarmsplat.slam.io.live import zenoh_config

    zenoh, conf = zenoh_config(connect=connect, listen=list(listen or []))
    session = zenoh.open(conf)
    t0 = last = time.monotonic()
    try:
        while time.monotonic() - t0 < timeout:
            for reply in session.get(f"swarmsplat/{run}/register", payload=name.encode(), timeout=2.0):
                if reply.ok is None:
                    continue
                answer = json.loads(reply.ok.payload.to_bytes())
                if "error" in answer:
                    raise SwarmsplatError(f"{name}: the team server refused this agent: {answer['error']}")
                return int(answer["index"])
            if say is not None and time.monotonic() - last > 5:
                last = time.monotonic()
                say(f"{name}: waiting for the team server to give this agent its index "
                    f"({last - t0:.0f} s)")
            time.sleep(0.2)
    finally:
        session.close()
    raise SwarmsplatError(f"{name}: no team server answered within {timeout:.0f} s (link.connect_timeout_s) on "
                          f"{', '.join(connect)}; is `swarmsplat server` running and reachable? (or give --id)")
