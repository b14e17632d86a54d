"""The team under random faults for minutes: `python -m perf soak --minutes M [--seed S] [--kinds K,...] [--faults N]
[--scratch DIR] [--json OUT] [--md OUT]`.

A generated team (3 agents, long sequences at 160x120) runs as `swarmsplat server` and one `swarmsplat agent
--server ... --out DIR` process per agent over Zenoh on localhost, sized to take about M minutes on 2 cores at load
~6. Faults come one at a time, at fractions of the agents' run drawn from the seed; the reference run (below) tells
how long the agents run on this machine, which turns them into seconds (the schedule is printed and saved):

  agent_kill     SIGKILL of an agent process; after a few seconds the same command with --resume
  server_kill    SIGKILL of the server; after a few seconds the same command (it replays link/journal.bin)
  link_cut       the agents reach the server through a TCP relay in this process; for 5-60 s it closes every
                 connection it carries and refuses new ones (checked: no connection reaches the server's port
                 meanwhile)
  disk_full      each agent's --out is a 128 MB tmpfs of its own; a ballast file fills it, the agent stops at its
                 next write (one line, exit 1), the ballast goes after a hold and the agent is started with
                 --resume (no tmpfs without the right to mount one: not run, and said so)
  corrupt_frame  an image of an agent's sequence a few frames ahead of where it is, cut to half its bytes
  clock_jump     the agent's camera clock steps from seconds since boot to Unix time (as an NTP sync at boot does):
                 the timestamps of its frames from one frame on, in its image lists and ground truth, jump by
                 ~1.7e9 s; written into the data before the start (the processes' own clocks are not touched)

The same seed runs first without faults (the reference, on the data before the faults). Checks afterwards:
every frame any agent tracked has its pose on disk (the server's trajectories/<agent>.txt and the agent's own
progress/poses.tum up to its last keyframe and trajectory.txt, each frame once); the team's result complete, every
agent joined, ATE within 10 % and merged PSNR within 0.5 dB of the reference; the resident memory of every process
life that lasts 20 s past the warm-up (a quarter of the soak, at least 20 s; the server while it serves) at most
10 % above its level after the warm-up. A soak of MEMORY_MINUTES or more must have such a life; in a shorter one,
where the processes may all end or be killed before (a fast machine ends the test's 1.25-minute soak in one), the
memory check is reported as not evaluated. Writes perf/results/soak-cpu.json / .md with the schedule, each fault's log (when,
what was done, what the team did: from the processes' logs, journals and metrics) and the checks.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import pickle
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from .common import machine_info, markdown_table, write_results

REPO = Path(__file__).resolve().parents[1]
KINDS = ("agent_kill", "server_kill", "link_cut", "disk_full", "corrupt_frame", "clock_jump")
ON_AGENT = ("agent_kill", "disk_full", "corrupt_frame", "clock_jump")
AGENTS, WIDTH, HEIGHT = 3, 160, 120
SECONDS_PER_ROUND = 0.8  # a round of 3 agents and the server at 160x120 on 2 shared cores (load ~6), measured
TMPFS_MB = 128
MEMORY_MINUTES = 5.0  # from this length on, a soak without a process life past the warm-up fails its memory check
CONFIG = {  # the team's logic at a small cost: a keyframe every 4 frames, a submap (and a checkpoint) every 4
    "mapping": {"iterations": 8, "first_iterations": 25},
    "tracking": {"refine": False},
    "keyframes": {"every": 4},
    "submaps": {"max_keyframes": 4},
    "loop_closure": {"min_index_gap": 2, "cloud_route": False},  # KISS-Matcher's threads: not bit-reproducible
    "server": {"tau_sim": 0.5, "cloud_route": False},
    "team": {"render_views": 4},
    "map_refine": {"iterations_per_keyframe": 2},
    "link": {"resend_s": 5.0},  # the default 30 s would stall the server that long after each restart
}


def draw_schedule(seed: int, minutes: float, kinds=KINDS, faults: int | None = None, frames: int = 0) -> list[dict]:
    """The faults, drawn from `seed`: every kind of `kinds` once (in random order), then random kinds up to
    `faults` (default: one every two minutes, at least one of each kind). Each fault's time `at` is a fraction of
    the agents' run (until the last agent process of the reference run ended: `timed` makes it seconds on this
    machine, so a fast machine gets its faults while its agents still run): 10-70 % for faults on an agent's
    process or frames, 10-90 % for the others."""
    rng = random.Random(seed)
    span = minutes * 60
    n = faults if faults is not None else max(len(kinds), round(minutes / 2))
    picks = list(kinds)
    rng.shuffle(picks)
    picks = (picks + [rng.choice(kinds) for _ in range(max(0, n - len(picks)))])[:n]
    times = [round(rng.uniform(0.1, 0.7) if k in ON_AGENT else rng.uniform(0.1, 0.9), 3) for k in picks]
    out = []
    for kind, t in sorted(zip(picks, times), key=lambda x: x[1]):
        f = {"kind": kind, "at": t, "agent": rng.randrange(AGENTS)}
        if kind == "agent_kill":
            f["down_s"] = round(rng.uniform(1, 10), 1)
        elif kind == "server_kill":
            f["down_s"], f["agent"] = round(rng.uniform(1, 10), 1), None
        elif kind == "link_cut":
            f["seconds"], f["agent"] = round(rng.uniform(5, min(60.0, max(5.0, 0.2 * span))), 1), None
        elif kind == "disk_full":
            f["hold_s"] = round(rng.uniform(5, 30), 1)
        elif kind == "corrupt_frame":
            f["ahead"], f["image"] = rng.randint(2, 10), rng.choice(["rgb", "depth"])
        elif kind == "clock_jump":
            f["frame"] = rng.randint(frames // 5, frames * 4 // 5) if frames else None
            f["jump_s"] = round(1.7e9 + rng.uniform(0, 1e8), 3)
        out.append(f)
    return out


def timed(schedule: list[dict], agents_s: float) -> list[dict]:
    """The schedule with each fault's time in seconds since the start (`at_s`), for agents that run `agents_s`."""
    return [{**f, "at_s": round(f["at"] * agents_s, 1)} for f in schedule]


# ---- the processes ---------------------------------------------------------------------------------------------

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
        for d in self.agent_dirs:
            d.mkdir(exist_ok=True)
            if tmpfs and subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_MB}m", "tmpfs", str(d)],
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


# ---- the faults ------------------------------------------------------------------------------------------------

def _wait_journal_growth(team: TeamRun, since: int, limit_s: float) -> float | None:
    """Seconds until the server's journal grows past `since` bytes (a message from an agent arrived), or None."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < limit_s:
        if team.journal_bytes() > since:
            return round(time.monotonic() - t0, 1)
        if team.done():
            return None
        time.sleep(0.2)
    return None


def agent_kill(team: TeamRun, f: dict) -> dict:
    role, d = f"agent_{f['agent']}", team.agent_dirs[f["agent"]]
    li = team.current(role)
    if not li.alive():
        return {"applied": False, "why": f"{role} had ended (exit {li.rc})"}
    frames, ckpt = _journal_frames(d / "progress" / "poses.tum"), _checkpoint_round(d)
    rc = li.kill()
    time.sleep(f["down_s"])
    new = team.start(role, resume=True)
    return {"applied": True, "exit": rc, "journal_frames_at_kill": frames, "checkpoint_round": ckpt,
            "restarted_pid": new.pid}


def server_kill(team: TeamRun, f: dict) -> dict:
    li = team.current("server")
    if not li.alive():
        return {"applied": False, "why": f"the server had ended (exit {li.rc})"}
    size = team.journal_bytes()
    rc = li.kill()
    time.sleep(f["down_s"])
    new = team.start("server")
    return {"applied": True, "exit": rc, "journal_bytes_at_kill": size, "restarted_pid": new.pid,
            "first_new_message_after_s": _wait_journal_growth(team, size, 120)}


def link_cut(team: TeamRun, f: dict) -> dict:
    if team.done():
        return {"applied": False, "why": "the team had finished"}
    team.relay.cut()
    t_end, bypass, size = time.monotonic() + f["seconds"], 0, None
    while time.monotonic() < t_end:  # nothing may reach the server's port while the relay is cut
        bypass = max(bypass, established_to(team.port))
        if size is None and time.monotonic() > t_end - f["seconds"] + 2:  # after what was on its way
            size = team.journal_bytes()
        time.sleep(0.5)
    grew = team.journal_bytes() - (size or team.journal_bytes())
    refused = team.relay.refused
    team.relay.restore()
    after = team.journal_bytes()
    return {"applied": True, "connections_reaching_server_during_cut": bypass,
            "journal_growth_during_cut_after_2s": grew, "reconnects_refused": refused, "first_message_after_restore_s": _wait_journal_growth(team, after, 120)}


def disk_full(team: TeamRun, f: dict) -> dict:
    role, d = f"agent_{f['agent']}", team.agent_dirs[f["agent"]]
    if d not in team.mounts:
        return {"applied": False, "why": "no tmpfs (mount -t tmpfs was refused: it needs root)"}
    li = team.current(role)
    if not li.alive():
        return {"applied": False, "why": f"{role} had ended (exit {li.rc})"}
    ballast, t0 = d / "ballast", time.monotonic()
    fd = os.open(ballast, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        for size in (1 << 20, 4096, 1):  # every byte of the tmpfs taken
            try:
                while os.write(fd, b"\0" * size):
                    pass
            except OSError:
                pass
    finally:
        os.close(fd)
    st = os.statvfs(d)
    while li.alive() and time.monotonic() - t0 < f["hold_s"]:
        time.sleep(0.2)
    stopped = not li.alive()
    t_stop = round(time.monotonic() - t0, 1) if stopped else None
    while time.monotonic() - t0 < f["hold_s"]:
        time.sleep(0.2)
    ballast.unlink()
    out = {"applied": True, "free_bytes_when_full": st.f_bavail * st.f_frsize, "agent_stopped": stopped,
           "stopped_after_s": t_stop}
    if stopped:
        time.sleep(0.5)
        li.handled = True  # restarted here, not by the supervisor
        out.update({"exit": li.rc, "its_last_line": next((ln for _, ln in reversed(li.lines) if ln), None),
                    "restarted_pid": team.start(role, resume=True).pid})
    return out


def _stamps(seq: Path) -> list[float]:
    return [float(ln.split()[0]) for ln in (seq / "rgb.txt").read_text().splitlines() if ln and ln[0] != "#"]


def corrupt_frame(team: TeamRun, f: dict) -> dict:
    """An image ahead of the drawn agent, or of the next agent that has frames left (the log's "agent")."""
    for k in [(f["agent"] + i) % AGENTS for i in range(AGENTS)]:
        seq = team.data / f"agent_{k}"
        done = _journal_frames(team.agent_dirs[k] / "progress" / "poses.tum")
        n = len(_stamps(seq))
        frame = done + CONFIG["keyframes"]["every"] + f["ahead"]  # the journal lags the agent by up to a keyframe
        if frame < n:
            break
    else:
        return {"applied": False, "why": f"every agent was within {f['ahead']} frames of its end"}
    path = seq / f["image"] / f"{frame:06d}.png"
    data = path.read_bytes()
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(data[: len(data) // 2])
    os.replace(tmp, path)
    return {"applied": True, "agent": k, "frame": frame, "file": str(path.relative_to(team.data)),
            "agent_at_frame": done}


def plant_clock_jump(seq: Path, frame: int, jump_s: float) -> None:
    """From `frame` on, every timestamp of the sequence (image lists, ground truth) jumps by `jump_s` seconds."""
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines, out, k = (seq / name).read_text().splitlines(), [], 0
        for ln in lines:
            if ln and ln[0] != "#":
                t, rest = ln.split(" ", 1)
                ln = f"{float(t) + (jump_s if k >= frame else 0.0):.6f} {rest}"
                k += 1
            out.append(ln)
        (seq / name).write_text("\n".join(out) + "\n")


def clock_jump(team: TeamRun, f: dict) -> dict:
    """Planted before the start (plant_clock_jump); here: where the agent stands now."""
    done = _journal_frames(team.agent_dirs[f["agent"]] / "progress" / "poses.tum")
    return {"applied": True, "frame": f["frame"], "jump_s": f["jump_s"], "agent_at_frame_now": done}


INJECT = {"agent_kill": agent_kill, "server_kill": server_kill, "link_cut": link_cut, "disk_full": disk_full,
          "corrupt_frame": corrupt_frame, "clock_jump": clock_jump}


def describe(f: dict) -> str:
    who = f"agent_{f['agent']}" if f.get("agent") is not None else "the team"
    extra = ", ".join(f"{k} {v}" for k, v in f.items() if k not in ("kind", "at", "at_s", "agent"))
    return f"{f['kind']} of {who}" + (f" ({extra})" if extra else "")


def run_team(data: Path, cfg: Path, root: Path, schedule: list[dict], *, timeout_s: float, say=print):
    """Run the team in `root`, injecting `schedule`'s faults one at a time. Returns (the TeamRun, the fault log)."""
    team = TeamRun(data, cfg, root, tmpfs=any(f["kind"] == "disk_full" for f in schedule))
    log, pending = [], list(schedule)
    team.begin()
    try:
        while not team.done():
            if team.now() > timeout_s:
                log.append({"kind": "timeout", "t_s": team.now(), "applied": True,
                            "why": f"the team had not finished after {timeout_s:.0f} s"})
                break
            team.supervise(log)
            if pending and team.now() >= pending[0]["at_s"]:
                f = pending.pop(0)
                t = team.now()
                say(f"[soak] {t:6.1f} s  {describe(f)}")
                res = INJECT[f["kind"]](team, f)
                log.append({**f, "t_s": t, "t_end_s": team.now(), **res})
                say(f"[soak] {team.now():6.1f} s    " + ", ".join(f"{k} {v}" for k, v in res.items()))
            time.sleep(0.2)
        log += [{**f, "applied": False, "why": "the team had finished"} for f in pending]
    finally:
        team.close()
        team.wall = team.now()
        (root / "logs").mkdir(exist_ok=True)
        for li in team.lives:  # each process life's output, timed from the start
            (root / "logs" / f"{li.role}-{li.pid}.log").write_text("".join(f"{t} {ln}\n" for t, ln in li.lines))
    return team, log


# ---- the checks ------------------------------------------------------------------------------------------------

def _tum_stamps(path: Path) -> list[float]:
    try:
        return [round(float(ln.split()[0]), 3) for ln in path.read_text().splitlines() if ln and ln[0] != "#"]
    except OSError:
        return []


def check_poses(data: Path, server_dir: Path, agent_dirs: list[Path], metrics: dict) -> list[dict]:
    """Every frame each agent tracked (its frames but the skipped ones) has its pose in the server's
    trajectories/<agent>.txt and the agent's trajectory.txt, once; the agent's progress/poses.tum holds each frame
    up to its last keyframe once, in order."""
    rows = []
    for k, d in enumerate(agent_dirs):
        name = f"agent_{k}"
        stamps = [round(t, 3) for t in _stamps(data / name)]
        agent = next((a for a in metrics.get("agents", []) if a["name"] == name), {})
        skipped = {int(s["frame"]) for s in agent.get("skipped_frames", [])}
        tracked = [t for i, t in enumerate(stamps) if i not in skipped]
        server = _tum_stamps(server_dir / "trajectories" / f"{name}.txt")
        own = _tum_stamps(d / "trajectory.txt")
        journal = _tum_stamps(d / "progress" / "poses.tum")
        upto = [t for t in tracked if journal and stamps.index(t) <= stamps.index(journal[-1])] \
            if journal and journal[-1] in stamps else tracked
        row = {"agent": name, "tracked": len(tracked), "skipped": sorted(skipped),
               "server_missing": len(set(tracked) - set(server)), "server_twice": len(server) - len(set(server)),
               "own_missing": len(set(tracked) - set(own)), "journal_frames": len(journal),
               "journal_missing": len(set(upto) - set(journal)), "journal_twice": len(journal) - len(set(journal)),
               "journal_in_order": journal == sorted(journal, key=stamps.index) if set(journal) <= set(stamps)
               else False, "journal_to_end": len(tracked) - len(upto)}
        row["ok"] = (row["server_missing"] == row["server_twice"] == row["own_missing"] == row["journal_missing"]
                     == row["journal_twice"] == 0 and row["journal_in_order"]
                     and row["journal_to_end"] <= CONFIG["keyframes"]["every"])
        rows.append(row)
    return rows


def check_memory(lives: list[Life], samples: list[dict], span_s: float, limit: float = 0.10) -> list[dict]:
    """Per process life lasting past the warm-up (a quarter of the soak, at least 20 s) by 20 s or more: its
    resident memory's peak after the warm-up against its median over the 20 s after it. The server counts while it
    serves (up to its last status line; its end, the evaluation and the merged map's refinement, is another load)."""
    warm = max(20.0, 0.25 * span_s)
    rows = []
    for li in lives:
        end = li.end if li.end is not None else span_s
        if li.role == "server":
            end = max((t for t, ln in li.lines if ln.startswith("[server] ")), default=li.start)
        series = [(s["t"], s["rss_mb"][str(li.pid)]) for s in samples
                  if str(li.pid) in s["rss_mb"] and s["t"] <= end]
        t_warm = li.start + warm
        if end - t_warm < 20 or not series:
            continue
        base = sorted(m for t, m in series if t_warm <= t <= t_warm + 20)
        after = [m for t, m in series if t >= t_warm]
        if not base or not after:
            continue
        b = base[len(base) // 2]
        growth = max(after) / b - 1
        rows.append({"process": li.role, "pid": li.pid, "from_s": round(li.start, 1), "to_s": round(end, 1),
                     "rss_start_mb": round(series[0][1]), "rss_after_warmup_mb": round(b),
                     "rss_peak_after_mb": round(max(after)), "growth_pct": round(100 * growth, 1),
                     "ok": growth <= limit})
    return rows


def _near(lines, t0, t1, *words) -> list[str]:
    return [f"{t} s {ln.strip()}" for t, ln in lines if t0 <= t <= t1 and any(w in ln for w in words)]


def _resumed(team: TeamRun, pid) -> str:
    """What the process life `pid` (a restarted agent) said of where it resumed."""
    li = next((x for x in team.lives if x.pid == pid), None)
    got = _near(li.lines, 0, 1e9, "resuming at round", "no checkpoint") if li else []
    return got[0] if got else f"it ended before saying where it resumed (exit {li.rc if li else None})"


def what_the_team_did(f: dict, team: TeamRun, metrics: dict) -> str:
    """From the processes' logs, journals and the final metrics: the team's answer to fault `f`."""
    if not f.get("applied"):
        return f"not applied: {f.get('why')}"
    t, t1 = f["t_s"], f.get("t_end_s", f["t_s"])
    lines = lambda role: [x for li in team.lives if li.role == role for x in li.lines]  # noqa: E731
    kind, role = f["kind"], f"agent_{f.get('agent')}"
    if kind == "agent_kill":
        return (f"killed at journal frame {f['journal_frames_at_kill']} (checkpoint: next round "
                f"{f['checkpoint_round']}); restarted with --resume: " + _resumed(team, f["restarted_pid"]))
    if kind == "server_kill":
        got = _near(lines("server"), t, t1 + 120, "replayed", "is back")
        first = f["first_new_message_after_s"]
        return ("the agents kept tracking; restarted server: " + "; ".join(got[:2]) + (
            f"; first new message {first} s after the restart" if first is not None else
            "; no new agent message after the restart (the agents had sent everything)"))
    if kind == "link_cut":
        got = _near(lines("server"), t, t1 + 60, "nothing heard", "is back")
        return (f"{f['reconnects_refused']} reconnects refused during the cut, "
                f"{f['connections_reaching_server_during_cut']} connections reached the server, its journal grew "
                f"{f['journal_growth_during_cut_after_2s']} bytes after the first 2 s; "
                + (f"first message {f['first_message_after_restore_s']} s after the link was back"
                   if f["first_message_after_restore_s"] is not None else "no agent message after the link was back "
                   "(the agents had sent everything)") + "".join("; " + g for g in got))
    if kind == "disk_full":
        if not f["agent_stopped"]:
            return f"{role} wrote nothing while the disk was full ({f['hold_s']} s)"
        return (f"{role} stopped after {f['stopped_after_s']} s, exit {f['exit']}: {f['its_last_line']!r}; "
                f"space freed, restarted with --resume: " + _resumed(team, f["restarted_pid"]))
    if kind == "corrupt_frame":
        agent = next((a for a in metrics.get("agents", []) if a["name"] == role), {})
        hit = [s for s in agent.get("skipped_frames", []) if int(s["frame"]) == f["frame"]]
        return f"frame {f['frame']} skipped: {hit[0]['reason']}" if hit else f"frame {f['frame']} NOT listed as skipped"
    if kind == "clock_jump":
        k = f["agent"]
        when = next((s["t"] for s in team.samples if s["frames"][k] > f["frame"]), None)
        stamps = set(_tum_stamps(team.server_dir / "trajectories" / f"{role}.txt"))
        late = len(stamps & {round(t, 3) for t in _stamps(team.data / role)[f["frame"]:]})
        return (f"{role} journaled frame {f['frame']} (the jump) by {when} s; the team's trajectory holds "
                f"{late} poses from the jump on, {len(stamps) - late} before")
    return json.dumps({k: v for k, v in f.items() if k not in ("kind",)})


# ---- the soak --------------------------------------------------------------------------------------------------

def prepare(scratch: Path, seed: int, minutes: float) -> tuple[Path, Path, int]:
    """The generated team (clean), the config file and the frames per agent, sized for `minutes`."""
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.synthetic import GeneratorConfig, generate
    from swarmsplat.slam.synthetic.config import MotionConfig

    frames = max(48, int(minutes * 60 / SECONDS_PER_ROUND))
    gen = GeneratorConfig.preset("tiny", seed=seed, agents=AGENTS, frames=frames, width=WIDTH, height=HEIGHT,
                                 motion=MotionConfig(loop_turns=min(5.0, max(1.3, frames / 100))))
    data = scratch / "data" if (scratch / "data" / "dataset.yaml").is_file() else generate(scratch / "data", gen)
    cfg = scratch / "config.yaml"
    cfg.write_text(SlamConfig().override(CONFIG).to_yaml())
    return data, cfg, frames


def soak(minutes: float, seed: int, scratch: Path, *, kinds=KINDS, faults: int | None = None, say=print) -> dict:
    """The reference run, then the soak, then the checks (module docstring). Returns the report."""
    data, cfg, frames = prepare(scratch, seed, minutes)
    schedule = draw_schedule(seed, minutes, kinds, faults, frames)
    (scratch / "schedule.json").write_text(json.dumps(schedule, indent=1))
    say(f"[soak] {AGENTS} agents x {frames} frames at {WIDTH}x{HEIGHT}, seed {seed}; schedule:")
    for f in schedule:
        say(f"[soak]   {100 * f['at']:5.1f} % of the agents' run  {describe(f)}")
    timeout = 4 * minutes * 60 + 600
    say("[soak] the reference run (no faults)")
    ref_team, ref_log = run_team(data, cfg, scratch / "reference", [], timeout_s=timeout, say=say)
    ref = _metrics(ref_team.server_dir)
    agents_s = max((li.end for li in ref_team.lives if li.role != "server" and li.end is not None),
                   default=ref_team.now())
    schedule = timed(schedule, agents_s)
    (scratch / "schedule.json").write_text(json.dumps(schedule, indent=1))
    say(f"[soak] reference: ATE {ref.get('ate_rmse_team')} m, PSNR {ref.get('psnr')} dB, "
        f"{ref_team.now():.0f} s (the agents {agents_s:.0f} s); the faults at "
        + ", ".join(f"{f['at_s']:.1f} s" for f in schedule))

    soak_data = scratch / "data_soak"
    shutil.rmtree(soak_data, ignore_errors=True)
    shutil.copytree(data, soak_data)
    for f in schedule:
        if f["kind"] == "clock_jump":
            plant_clock_jump(soak_data / f"agent_{f['agent']}", f["frame"], f["jump_s"])
    say("[soak] the soak")
    team, log = run_team(soak_data, cfg, scratch / "soak", schedule, timeout_s=timeout, say=say)
    span = team.now()
    m = _metrics(team.server_dir)
    for f in log:
        f["team_did"] = what_the_team_did(f, team, m)
    poses = check_poses(soak_data, team.server_dir, team.agent_dirs, m)
    memory = check_memory(team.lives, team.samples, span)
    ref_memory = check_memory(ref_team.lives, ref_team.samples, ref_team.now())
    if team.mounts:
        team.unmount(scratch / "soak_agents")
    checks = result_checks(m, ref, poses, memory, log, memory_required=minutes >= MEMORY_MINUTES, span_s=span)
    return {"seed": seed, "minutes": minutes, "agents": AGENTS, "frames_per_agent": frames, "size": [WIDTH, HEIGHT],
            "config": CONFIG, "schedule": schedule, "faults": log, "checks": checks, "poses": poses,
            "memory": memory, "reference_memory": ref_memory, "wall_s": {"soak": span, "reference": ref_team.now(),
                                                                    "reference_agents": agents_s},
            "soak": _summary(m), "reference": _summary(ref), "disk_full_tmpfs": team.tmpfs,
            "lives": [li.info() for li in team.lives], "unexpected_in_reference": ref_log,
            "samples": team.samples[::5]}


def _metrics(out: Path) -> dict:
    try:
        return json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError):
        return {}


def _summary(m: dict) -> dict:
    link = m.get("link", {})
    return {"status": m.get("status"), "ate_team_cm": None if m.get("ate_rmse_team") is None else
            round(100 * m["ate_rmse_team"], 4), "psnr": m.get("psnr"), "loops": m.get("loops_accepted"),
            "candidates": m.get("loop_candidates"), "all_agents_joined": m.get("all_agents_joined"),
            "lost_agents": link.get("lost_agents"), "replayed_messages": link.get("replayed_messages"),
            "keyframes": [a.get("keyframes") for a in m.get("agents", [])],
            "frames_tracked": [a.get("frames_tracked") for a in m.get("agents", [])],
            "repeats_received": {k: v.get("repeats_received") for k, v in link.get("agents", {}).items()},
            "resent": {k: v.get("agent_side", {}).get("resent") for k, v in link.get("agents", {}).items()}}


def result_checks(m: dict, ref: dict, poses: list[dict], memory: list[dict], log: list[dict], *,
                  memory_required: bool = True, span_s: float | None = None) -> dict:
    """Each invariant: {"ok": bool, "detail": str}; "ok" is None for the memory check of a short soak
    (memory_required false) in which no process life lasted past the warm-up: not evaluated, neither passed nor
    failed."""
    ate, ate_ref = m.get("ate_rmse_team"), ref.get("ate_rmse_team")
    psnr, psnr_ref = m.get("psnr"), ref.get("psnr")
    lost = m.get("link", {}).get("lost_agents")
    return {
        "complete": {"ok": m.get("status") == "complete" and bool(m.get("all_agents_joined")) and lost == [],
                     "detail": f"status {m.get('status')}, all agents joined {m.get('all_agents_joined')}, "
                               f"lost {lost}"},
        "no_timeout": {"ok": not any(f["kind"] == "timeout" for f in log), "detail": "the team finished"},
        "poses_on_disk": {"ok": bool(poses) and all(r["ok"] for r in poses),
                          "detail": "; ".join(f"{r['agent']}: {r['tracked']} tracked, missing server "
                                              f"{r['server_missing']} / own {r['own_missing']} / journal "
                                              f"{r['journal_missing']}" for r in poses)},
        "ate_within_10pct": {"ok": bool(ate and ate_ref) and abs(ate / ate_ref - 1) <= 0.10,
                             "detail": f"{_cm(ate)} cm against {_cm(ate_ref)} cm"
                                       + (f" ({100 * (ate / ate_ref - 1):+.1f} %)" if ate and ate_ref else "")},
        "psnr_within_0.5dB": {"ok": psnr is not None and psnr_ref is not None and abs(psnr - psnr_ref) <= 0.5,
                              "detail": f"{psnr} dB against {psnr_ref} dB"},
        "memory_flat": _memory_check(memory, memory_required, span_s),
    }


def _memory_check(memory: list[dict], required: bool, span_s: float | None) -> dict:
    if memory:
        return {"ok": all(r["ok"] for r in memory),
                "detail": "; ".join(f"{r['process']} (pid {r['pid']}) {r['growth_pct']:+.1f} %" for r in memory)}
    took = f" (the soak took {span_s:.0f} s)" if span_s is not None else ""
    if required:
        return {"ok": False, "detail": f"no process life lasted 20 s past the warm-up{took}"}
    return {"ok": None, "detail": f"not evaluated: no process life lasted 20 s past the warm-up{took}; a soak of "
                                  f"{MEMORY_MINUTES:g} minutes or more evaluates it"}


def _cm(x):
    return None if x is None else round(100 * x, 4)


def markdown(report: dict) -> str:
    r = report
    md = [f"# soak: {r['agents']} agent processes and a server over Zenoh, {r['minutes']} minutes of faults "
          f"(seed {r['seed']})", "",
          f"{r['agents']} generated agents x {r['frames_per_agent']} frames at {r['size'][0]}x{r['size'][1]}; "
          f"the soak took {r['wall_s']['soak']:.0f} s, the reference (same seed, no faults) "
          f"{r['wall_s']['reference']:.0f} s. Disk full on a tmpfs: {'yes' if r['disk_full_tmpfs'] else 'no'}.", "",
          "## Checks", "",
          markdown_table([{"check": k, "ok": {True: "yes", None: "not evaluated"}.get(v["ok"], "**NO**"),
                                            "detail": v["detail"]}
                          for k, v in r["checks"].items()], ["check", "ok", "detail"]), "",
          "## Faults", "",
          markdown_table([{"t_s": f.get("t_s", f.get("at_s")), "fault": describe({k: v for k, v in f.items()
                                                                                 if k in ("kind", "agent")}),
                           "parameters": ", ".join(f"{k} {f[k]}" for k in ("down_s", "seconds", "hold_s", "frame",
                                                                          "jump_s", "image") if k in f),
                           "what the team did": f.get("team_did", "")} for f in r["faults"]],
                         ["t_s", "fault", "parameters", "what the team did"]), "",
          "## Results", "",
          markdown_table([{"run": name, **{k: v for k, v in r[name].items() if not isinstance(v, dict)}}
                          for name in ("reference", "soak")],
                         ["run", "status", "ate_team_cm", "psnr", "loops", "candidates", "keyframes",
                          "frames_tracked", "replayed_messages", "lost_agents"]), "",
          f"- repeats received by the server (soak): {r['soak']['repeats_received']}; messages resent by the agents' "
          f"last processes: {r['soak']['resent']}", "",
          "## Memory (resident, per process life)", "",
          markdown_table(r["memory"], ["process", "pid", "from_s", "to_s", "rss_start_mb", "rss_after_warmup_mb",
                                       "rss_peak_after_mb", "growth_pct", "ok"]), "",
          "Reference run, the same measure: " + "; ".join(f"{x['process']} {x['growth_pct']:+.1f} %"
                                                         for x in r["reference_memory"]), "",
          "## Poses on disk", "",
          markdown_table(r["poses"], ["agent", "tracked", "skipped", "server_missing", "server_twice", "own_missing",
                                      "journal_frames", "journal_missing", "journal_twice", "journal_to_end", "ok"]),
          ""]
    return "\n".join(md)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf soak", description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=5.0, help="how long the soak runs (the sequences are sized "
                                                               "for it; the reference run takes about as long)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--kinds", default=",".join(KINDS), help="the fault kinds, comma-separated")
    p.add_argument("--faults", type=int, help="how many faults (default: one every two minutes, each kind once)")
    p.add_argument("--scratch", help="keep the runs here (default: a temporary folder)")
    p.add_argument("--json", dest="json_out", default=str(REPO / "perf" / "results" / "soak-cpu.json"))
    p.add_argument("--md", dest="md_out", default=str(REPO / "perf" / "results" / "soak-cpu.md"))
    args = p.parse_args(argv)
    kinds = tuple(k for k in args.kinds.split(",") if k)
    if not kinds or set(kinds) - set(KINDS):
        p.error(f"--kinds: choose from {', '.join(KINDS)}")
    # a soak stopped with Ctrl-C or SIGTERM (even when started in the background) still ends its processes and
    # unmounts its tmpfs
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    info = machine_info()  # before the run: the load it started under
    with tempfile.TemporaryDirectory(prefix="swarmsplat-soak-") as tmp:
        scratch = Path(args.scratch or tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        report = soak(args.minutes, args.seed, scratch, kinds=kinds, faults=args.faults,
                      say=lambda s: print(s, file=sys.stderr, flush=True))
    report["machine"] = info
    md = markdown(report)
    write_results(args.json_out, args.md_out, report, md)
    print(md)
    return 0 if all(c["ok"] is not False for c in report["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
