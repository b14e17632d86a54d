"""The team a soak runs (perf/soak.py): its size and config, and its processes — `swarmsplat server`, one
`swarmsplat agent --server ... --out DIR` per agent and a TCP relay between them — started, watched (resident
memory, log lines) and restarted by the harness."""

from __future__ import annotations

import atexit
import math
import os
import pickle
import random
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
KINDS = ("agent_kill", "server_kill", "link_cut", "disk_full", "corrupt_frame", "clock_jump")
ON_AGENT = ("agent_kill", "disk_full", "corrupt_frame", "clock_jump")
AGENTS, WIDTH, HEIGHT = 3, 160, 120
SECONDS_PER_ROUND = 0.8  # a round of 3 agents and the server at 160x120 on 2 shared cores (load ~6), measured
TMPFS_MB = 128  # each agent's --out under disk_full, at least; and per frame of its sequence:
TMPFS_MB_PER_FRAME = 0.15  # an agent's checkpoint grows with its map (~60 MB at frame ~1,030 at 160x120) and is
# written beside the previous one: a 20-minute soak's agents filled 128 MB on their own at frames 1,026-1,041


def tmpfs_mb(frames: int) -> int:
    """The size (MB) of an agent's tmpfs for a sequence of `frames`: room for two checkpoints, the ballast fills the
    rest when a disk_full fault comes."""
    return max(TMPFS_MB, math.ceil(TMPFS_MB_PER_FRAME * frames))
MEMORY_MINUTES = 5.0  # from this length on, a soak without a process life past the warm-up fails its memory check
CONFIG = {  # the team's logic at a small cost: a keyframe every 4 frames, a submap (and a checkpoint) every 4
    "mapping": {"iterations": 8, "first_iterations": 25},
    "tracking": {"refine": False},
    "keyframes": {"every": 4},
    "submaps": {"max_keyframes": 4},
    # KISS-Matcher's threads are not bit-reproducible: no cloud route. One descriptor and one pose candidate per
    # keyframe and one inter-agent candidate (defaults 3, 2, 2): the server verifies every agent's candidates, and
    # with the defaults it fell minutes behind three agents sharing two cores (3 x 600 frames: the agents ended at
    # 180 s, the server had taken their keyframes at 361 s; with these, at 257 s)
    "loop_closure": {"min_index_gap": 2, "cloud_route": False, "top_k": 1, "pose_top_k": 1},
    "server": {"tau_sim": 0.5, "cloud_route": False, "top_k": 1},
    "team": {"render_views": 4},
    "map_refine": {"iterations_per_keyframe": 2},
    "link": {"resend_s": 5.0},  # the default 30 s would stall the server that long after each restart
}

class Life:
    """One process life: its command, pid, start and end (seconds since the soak began), exit code, log lines."""

    def __init__(self, role: str, cmd: list[str], t0: float, env: dict):
        self.role, self.t0, self.lines = role, t0, []
        self.start = time.monotonic() - t0
        self.p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                                  start_new_session=True)
        self.pid, self.end, self.rc = self.p.pid, None, None
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append((round(time.monotonic() - self.t0, 1), line.rstrip()))
        self.rc = self.p.wait()
        self.end = round(time.monotonic() - self.t0, 1)

    def alive(self) -> bool:
        return self.p.poll() is None

    def kill(self) -> int:
        if self.alive():
            self.p.send_signal(signal.SIGKILL)
        self.p.wait(30)
        t_end = time.monotonic() + 10
        while self.end is None and time.monotonic() < t_end:  # the reader saw the end
            time.sleep(0.05)
        return self.p.returncode

    def info(self) -> dict:
        return {"role": self.role, "pid": self.pid, "start_s": round(self.start, 1), "end_s": self.end,
                "exit": self.rc, "log_tail": [f"{t} {ln}" for t, ln in self.lines[-6:]]}


class Relay:
    """A TCP relay on localhost: agents connect to `port`, each connection is carried to `upstream`. While cut, every
    carried connection is closed and new ones are accepted and closed at once."""

    def __init__(self, upstream: int):
        self.upstream, self.cut_now, self.refused, self.carried = upstream, False, 0, 0
        self.lsock = socket.socket()
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind(("127.0.0.1", 0))
        self.lsock.listen(64)
        self.port = self.lsock.getsockname()[1]
        self._lock, self._socks, self._closed = threading.Lock(), [], False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                down, _ = self.lsock.accept()
            except OSError:
                return
            if self.cut_now:
                self.refused += 1
                down.close()
                continue
            try:
                up = socket.create_connection(("127.0.0.1", self.upstream), timeout=2)
            except OSError:  # the server is down: the agent's Zenoh retries
                down.close()
                continue
            up.settimeout(None)
            with self._lock:
                self._socks += [down, up]
                self.carried += 1
            for a, b in ((down, up), (up, down)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(1 << 16):
                b.sendall(data)
        except OSError:
            pass
        for s in (a, b):
            self._drop(s)

    def _drop(self, s: socket.socket) -> None:
        try:
            s.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        s.close()
        with self._lock:
            if s in self._socks:
                self._socks.remove(s)

    def cut(self) -> None:
        self.cut_now = True
        with self._lock:
            socks = list(self._socks)
        for s in socks:
            self._drop(s)

    def restore(self) -> None:
        self.cut_now = False

    def close(self) -> None:
        self._closed = True
        self.cut()
        self.lsock.close()


def established_to(port: int) -> int:
    """TCP connections established to a local `port` now (Linux /proc/net/tcp, tcp6)."""
    n = 0
    for name in ("tcp", "tcp6"):
        try:
            rows = Path(f"/proc/net/{name}").read_text().splitlines()[1:]
        except OSError:
            continue
        for r in rows:
            f = r.split()
            n += int(f[1].rsplit(":", 1)[1], 16) == port and f[3] == "01"
    return n


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _journal_frames(path: Path) -> int:
    try:
        return sum(1 for ln in path.read_text().splitlines() if ln and not ln.startswith("#"))
    except OSError:
        return 0


def _checkpoint_round(folder: Path) -> int | None:
    try:
        with open(folder / "progress" / "checkpoint.pkl", "rb") as f:
            return int(pickle.load(f)["next_frame"])
    except (OSError, EOFError, pickle.UnpicklingError, KeyError, TypeError):
        return None


class TeamRun:
    """A server and AGENTS agent processes on `data`, in `root`, with a relay between them; faults and samples
    timed from the start. tmpfs: mount a small tmpfs as each agent's --out (for disk_full)."""

    def __init__(self, data: Path, cfg: Path, root: Path, *, tmpfs: bool = False):
        self.data, self.cfg, self.root = data, cfg, root
        shutil.rmtree(root, ignore_errors=True)  # an earlier run's journal and checkpoints are not this run's
        root.mkdir(parents=True)
        self.server_dir = root / "server"
        self.agent_dirs = [root / f"agent_{k}" for k in range(AGENTS)]
        self.mounts = []
        rgb = data / "agent_0" / "rgb"
        size = tmpfs_mb(sum(1 for _ in rgb.iterdir()) if rgb.is_dir() else 0)
        for d in self.agent_dirs:
            d.mkdir(exist_ok=True)
            if tmpfs and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}m", "tmpfs", str(d)],
                                        capture_output=True).returncode == 0:
                self.mounts.append(d)
        self.tmpfs = bool(self.mounts)
        if self.mounts:
            atexit.register(self._umount)
        self.port, self.run_name = _free_port(), f"soak{os.getpid()}x{random.randrange(1 << 20)}"
        self.relay = Relay(self.port)
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.lives: list[Life] = []
        self.samples: list[dict] = []  # per 2 s: t, rss per live pid, journal frames per agent, server journal bytes
        self.t0, self.wall = time.monotonic(), None
        self._stop = threading.Event()

    def now(self) -> float:
        return self.wall if self.wall is not None else round(time.monotonic() - self.t0, 1)

    def _cmd(self, role: str, resume: bool = False) -> list[str]:
        base = [sys.executable, "-m", "swarmsplat.slam"]
        if role == "server":
            return base + ["server", "--agents", str(AGENTS), "--out", str(self.server_dir), "--config",
                           str(self.cfg), "--dataset", str(self.data), "--listen", f"tcp/127.0.0.1:{self.port}",
                           "--run", self.run_name, "--ros-keys", "off"]
        k = int(role.split("_")[1])
        return base + ["agent", str(self.data), "--id", str(k), "--name", role, "--server",
                       f"tcp/127.0.0.1:{self.relay.port}", "--config", str(self.cfg), "--run", self.run_name,
                       "--out", str(self.agent_dirs[k]), *(["--resume"] if resume else [])]

    def start(self, role: str, resume: bool = False) -> Life:
        life = Life(role, self._cmd(role, resume), self.t0, self.env)
        self.lives.append(life)
        return life

    def current(self, role: str) -> Life:
        return [li for li in self.lives if li.role == role][-1]

    def begin(self) -> None:
        self.t0 = time.monotonic()
        self.start("server")
        for k in range(AGENTS):
            self.start(f"agent_{k}")
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while not self._stop.wait(2.0):
            s = {"t": self.now(), "rss_mb": {}, "frames": [], "journal_bytes": 0}
            for li in self.lives:
                if li.alive() and (mb := _rss_mb(li.pid)) is not None:
                    s["rss_mb"][str(li.pid)] = round(mb, 1)
            s["frames"] = [_journal_frames(d / "progress" / "poses.tum") for d in self.agent_dirs]
            j = self.server_dir / "link" / "journal.bin"
            s["journal_bytes"] = j.stat().st_size if j.is_file() else 0
            self.samples.append(s)

    def journal_bytes(self) -> int:
        j = self.server_dir / "link" / "journal.bin"
        return j.stat().st_size if j.is_file() else 0

    def done(self) -> bool:
        return all(not self.current(r).alive() for r in ["server"] + [f"agent_{k}" for k in range(AGENTS)])

    def supervise(self, log: list) -> None:
        """Start again, with --resume, a process that ended with an error outside a fault (what a robot's supervisor
        would do); each such restart is logged as an unexpected exit."""
        for role in ["server"] + [f"agent_{k}" for k in range(AGENTS)]:
            li = self.current(role)
            if not li.alive() and li.rc not in (0, None, -signal.SIGKILL) and not getattr(li, "handled", False):
                li.handled = True
                log.append({"kind": "unexpected_exit", "t_s": self.now(), "role": role, "exit": li.rc,
                            "last_lines": [ln for _, ln in li.lines[-3:]]})
                if len([x for x in self.lives if x.role == role]) < 6:
                    self.start(role, resume=role != "server")

    def close(self) -> None:
        self._stop.set()
        for li in self.lives:
            if li.alive():
                li.kill()
        self.relay.close()

    def unmount(self, keep: Path) -> None:
        """Copy the agents' folders (without checkpoints) to `keep`, then unmount their tmpfs."""
        for d in self.agent_dirs:
            shutil.copytree(d, keep / d.name, dirs_exist_ok=True, ignore=shutil.ignore_patterns("*.pkl", "ballast"))
        self._umount()

    def _umount(self) -> None:
        for d in self.mounts:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)
        self.mounts = []


