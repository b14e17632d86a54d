"""What an interrupted or failed run writes (slam.run.guard): the same files a complete run writes where they
cost no evaluation — trajectories (TUM), the maps of the submaps built so far (3DGS PLY), loops.csv and a
metrics.json with "status" ("interrupted" | "failed") and "reason" — each atomically, each on its own, so one
that cannot be written (listed under "partial_errors") does not cost the others.

Evaluation (ATE, rendering) is left out: it can take minutes on a long run, and the user is waiting for the
process to end. `swarmsplat eval --gt <sequence> --est <out>/trajectory.txt` scores a partial trajectory later.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from .runtime import kernels_record

EVAL_NOTE = "partial result: no evaluation was run; score the trajectory with `swarmsplat eval`"


def _attempt(done: list[str], errors: dict, name: str, write: Callable[[], object]) -> None:
    try:
        write()
        done.append(name)
    except Exception as e:  # noqa: BLE001 - one output failing must not cost the others
        errors[name] = f"{type(e).__name__}: {e}"


def agent_counts(agent) -> dict:
    """The counters of one agent that need no evaluation (metrics.json of a complete run has them too)."""
    return {"frames_tracked": len(agent.poses), "skipped_frames": agent.skipped_frames(),
            "keyframes": len(agent.keyframes), "submaps": len(agent.gmap.submaps), "gaussians": len(agent.gmap)}


def write_partial_agent(agent, out: Path, *, status: str, reason: str, n_frames: int, wall_s: float) -> Path:
    """One agent's run cut short (slam.run.sequence.run_sequence): trajectory.txt, map.ply, loops.csv, metrics.json."""
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.run.sequence import _write_loops_csv
    from swarmsplat.slam.io.trajectory import write_tum

    out = Path(out)
    done, errors = [], {}
    stamps, T = agent.trajectory(per_keyframe=True)
    if len(stamps):
        _attempt(done, errors, "trajectory.txt", lambda: write_tum(out / "trajectory.txt", stamps, T))
    if agent.gmap.submaps:
        _attempt(done, errors, "map.ply", lambda: save_ply(out / "map.ply", agent.display_map(), max_color=None))
    _attempt(done, errors, "loops.csv", lambda: _write_loops_csv(out / "loops.csv", agent.loops.log_rows()))
    t = agent.time
    counts = agent_counts(agent)
    metrics = {
        "status": status, "reason": reason, "agent": agent.name, "frames": n_frames,
        "frames_processed": counts["frames_tracked"] + len(counts["skipped_frames"]), **counts,
        "loop_candidates": len(agent.loops.log), "loops_accepted": sum(1 for c in agent.loops.log if c.accepted),
        "pose_graph_optimisations": agent.loops.optimisations,
        "time_s": {"total": wall_s, "tracking": t.tracking, "mapping": t.mapping, "loop_closure": t.loop_closure},
        "kernels": kernels_record(agent.cfg.kernels), "note": EVAL_NOTE,
    }
    _finish(out, metrics, done, errors)
    return out


def write_partial_team(team, ds, out: Path, *, status: str, reason: str, wall_s: float, run_info: dict) -> Path:
    """A team run cut short (slam.run.team.run_team): trajectories/ and trajectories_no_lc/ (TUM), map.ply and
    map_<agent>.ply per component, loops.csv, config.yaml, server.yaml, metrics.json."""
    import yaml

    from swarmsplat.kernels.fileio import atomic_write_text

    from swarmsplat.slam.dense.loops.loop_log import summarise, write_loops_csv
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.io.trajectory import write_tum

    out = Path(out)
    srv = team.server
    names = [ag.name for ag in team.agents]
    done, errors = [], {}
    _attempt(done, errors, "config.yaml", lambda: atomic_write_text(out / "config.yaml", team.cfg.to_yaml()))
    _attempt(done, errors, "server.yaml", lambda: atomic_write_text(
        out / "server.yaml", yaml.safe_dump(srv.cfg.model_dump(mode="json"), sort_keys=False)))
    for a, name in enumerate(names):
        if not team.agents[a].poses:
            continue
        _attempt(done, errors, f"trajectories/{name}.txt",
                 lambda a=a, name=name: write_tum(out / "trajectories" / f"{name}.txt", *team.trajectory(a)))
        _attempt(done, errors, f"trajectories_no_lc/{name}.txt",
                 lambda a=a, name=name: write_tum(out / "trajectories_no_lc" / f"{name}.txt",
                                                  *team.trajectory_no_lc(a)))
    maps = {}
    for root, members in srv.components().items():
        if not any(team.agents[m].gmap.submaps for m in members):
            continue
        fname = "map.ply" if root == 0 else f"map_{names[root]}.ply"
        _attempt(done, errors, fname, lambda root=root, fname=fname: save_ply(out / fname, srv.display_map(root), max_color=None))
        maps[fname] = [names[m] for m in members]
    _attempt(done, errors, "loops.csv", lambda: write_loops_csv(out / "loops.csv", srv.records))
    summary = summarise(srv.records)
    agents = []
    for a, (ag, seq) in enumerate(zip(team.agents, ds.agents)):
        counts = agent_counts(ag)
        agents.append({"name": ag.name, "frames": len(seq),
                       "frames_processed": counts["frames_tracked"] + len(counts["skipped_frames"]),
                       **counts, "component": names[srv.slots[a].component],
                       "in_global_frame": srv.slots[a].component == 0,
                       "time_s": {"tracking": ag.time.tracking, "mapping": ag.time.mapping}})
    metrics = {
        "status": status, "reason": reason, "dataset": str(ds.root), "dataset_name": ds.name, "agents": agents,
        "components": {names[r]: [names[m] for m in ms] for r, ms in srv.components().items()}, "maps": maps,
        "gaussians": sum(len(ag.gmap) for ag in team.agents), "loops": summary,
        "loops_accepted": summary["intra"]["accepted"] + summary["inter"]["accepted"],
        "loop_candidates": len(srv.records), "pose_graph_optimisations": srv.optimisations,
        "time_s": {"wall": wall_s, "server": dict(srv.time)}, "kernels": kernels_record(team.cfg.kernels),
        "run": run_info, "note": EVAL_NOTE,
    }
    _finish(out, metrics, done, errors)
    return out


def _finish(out: Path, metrics: dict, done: list[str], errors: dict) -> None:
    from swarmsplat.slam.io.jsonio import write_json

    metrics["written"] = done + ["metrics.json"]
    if errors:
        metrics["partial_errors"] = errors
    metrics["written_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    write_json(out / "metrics.json", metrics)
