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
  disk_full      each agent's --out is a tmpfs of its own (128 MB, or 0.15 MB a frame for long sequences: two of its
                 checkpoints); a ballast file fills it, the agent stops at its
                 next write (one line, exit 1), the ballast goes after a hold and the agent is started with
                 --resume (no tmpfs without the right to mount one: not run, and said so)
  corrupt_frame  an image of an agent's sequence a few frames ahead of where it is, cut to half its bytes
  clock_jump     the agent's camera clock steps from seconds since boot to Unix time (as an NTP sync at boot does):
                 the timestamps of its frames from one frame on, in its image lists and ground truth, jump by
                 ~1.7e9 s; written into the data before the start (the processes' own clocks are not touched)

The same seed runs first without faults (the reference, on the data before the faults). Checks afterwards:
every frame any agent tracked has its pose on disk (the server's trajectories/<agent>.txt and the agent's own
progress/poses.tum up to its last keyframe and trajectory.txt, each frame once); the team's result complete, every
agent joined, ATE within 10 % and merged PSNR within 0.5 dB of the reference; the memory of every process life that
lasts 20 s past the warm-up (a quarter of the soak, at least 20 s; the server while it serves) at most 10 % above
its level after the warm-up, counting what it holds beyond its map: resident memory less the keyframes, Gaussians,
caches and queued messages its status lines report held (slam.dense.team.held; the server keeps the whole team's
map in memory, which grows with the mission by design, and is reported beside). A soak of MEMORY_MINUTES or more must have such a life; in a shorter one,
where the processes may all end or be killed before (a fast machine ends the test's 1.25-minute soak in one), the
memory check is reported as not evaluated. Writes perf/results/soak-cpu.json / .md with the schedule, each fault's
log (when, what was done, what the team did: from the processes' logs, journals and metrics) and the checks.

This file holds the schedule, the two runs and the report; the team and its processes are in perf/soak_team.py,
the faults in perf/soak_faults.py, the checks in perf/soak_checks.py.
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import signal
import sys
import tempfile
from pathlib import Path

from .common import machine_info, markdown_table, write_results
from .soak_checks import check_memory, check_poses, result_checks, what_the_team_did
from .soak_faults import describe, plant_clock_jump, run_team
from .soak_team import (AGENTS, CONFIG, HEIGHT, KINDS, MEMORY_MINUTES, ON_AGENT, REPO, SECONDS_PER_ROUND,
                        WIDTH)



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
            "repeats_received": {k: (v or {}).get("repeats_received") for k, v in link.get("agents", {}).items()},
            # an agent lost before its last process ended has no agent side
            "resent": {k: ((v or {}).get("agent_side") or {}).get("resent") for k, v in link.get("agents", {}).items()}}


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
          "What a process holds beyond its map (resident memory less the keyframes, Gaussians, caches and queued "
          "messages its status lines report held), after the warm-up and at its peak; held_* is the map's own "
          "growth.", "",
          markdown_table(r["memory"], ["process", "pid", "from_s", "to_s", "measure", "after_warmup_mb",
                                       "peak_after_mb", "growth_pct", "rss_start_mb", "rss_peak_after_mb",
                                       "held_after_warmup_mb", "held_end_mb", "ok"]), "",
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
