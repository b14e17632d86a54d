"""The soak's faults (perf/soak.py): each kind injected into a running team, and the loop that runs a team and
injects a schedule one fault at a time."""

from __future__ import annotations

import os
import time
from pathlib import Path


from .soak_team import AGENTS, CONFIG, TeamRun, _checkpoint_round, _journal_frames, established_to


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


