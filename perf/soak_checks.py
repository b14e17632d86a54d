"""The soak's checks (perf/soak.py): every tracked pose on disk, memory flat after the warm-up, the result against
the reference, and what the team did after each fault."""

from __future__ import annotations

import json
import re
from pathlib import Path


from .soak_faults import _stamps
from .soak_team import CONFIG, MEMORY_MINUTES, Life, TeamRun


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


_HELD = re.compile(r"held (\d+) MB")


def _beyond_held(li: Life, series: list[tuple[float, float]]) -> list[tuple[float, float, float]] | None:
    """(t, resident MB, MB held) at each of the life's status lines that report what it holds (the map and the
    messages in flight: slam.dense.team.held), against the resident sample nearest it (within 3 s); None: its lines
    report nothing held."""
    out = []
    for t, ln in li.lines:
        if (m := _HELD.search(ln)) and series:
            ts, rss = min(series, key=lambda x: abs(x[0] - t))
            if abs(ts - t) <= 3.0:
                out.append((t, rss, float(m.group(1))))
    return out or None


def check_memory(lives: list[Life], samples: list[dict], span_s: float, limit: float = 0.10) -> list[dict]:
    """Per process life lasting past the warm-up (a quarter of the soak, at least 20 s) by 20 s or more: its memory
    after the warm-up at its peak against its median over the 20 s after it. The memory measured is what the process
    holds beyond its map: resident memory less the arrays it reports holding in its status lines (the server keeps
    every agent's keyframes and Gaussians, an agent its own keyframes and poses: their growth is the map's, shown
    in the columns held_*), or resident memory alone for a process that reports nothing held. The server counts
    while it serves (up to its last status line; its end, the evaluation and the merged map's refinement, is
    another load)."""
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
        held = _beyond_held(li, series)
        measured = [(t, rss - h, h) for t, rss, h in held] if held else [(t, m, 0.0) for t, m in series]
        base = sorted((m, h) for t, m, h in measured if t_warm <= t <= t_warm + 20)
        after = [(m, h) for t, m, h in measured if t >= t_warm]
        if not base or not after:
            continue
        b, h0 = base[len(base) // 2]
        peak = max(after)
        growth = peak[0] / b - 1
        rss_after = [m for t, m in series if t >= t_warm]
        rows.append({"process": li.role, "pid": li.pid, "from_s": round(li.start, 1), "to_s": round(end, 1),
                     "measure": "beyond held" if held else "resident",
                     "rss_start_mb": round(series[0][1]), "rss_peak_after_mb": round(max(rss_after)),
                     "held_after_warmup_mb": round(h0), "held_end_mb": round(measured[-1][2]),
                     "after_warmup_mb": round(b), "peak_after_mb": round(peak[0]), "growth_pct": round(100 * growth, 1),
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


