"""Outputs of a swarm run, in-process or over Zenoh, all in one folder:

    config.yaml              the config tree the run used (its `swarm` section drives the robots)
    <agent>.txt              each robot's keyframe trajectory in the global frame it holds (TUM, evo reads it)
    odometry/<agent>.txt     each robot's own odometry at its keyframes (the no-collaboration reference)
    pose_graph_optimized.g2o the final global graph, solved as configured (vertices = optimised poses)
    metrics.json             ATE per robot and merged (one alignment) for the run, for odometry only and for the
                             other formulations re-solved on the same final graphs; loops; bytes per message type;
                             how each robot's end protocol ended (`end`: status, ticks, group, missing robots)
    trajectories.png         every robot against ground truth after the merged alignment
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_write_text

from swarmsplat.slam.flocc.swarm.optimiser import solve_group

ALTERNATIVES = {  # name -> (formulation, solver, uniform noise); "baseline" is Swarm-SLAM-like
    "is-lm": ("is", "lm", False), "ss-lm": ("ss", "lm", False), "base-lm": ("base", "lm", False),
    "is-gnc": ("is", "gnc", False), "baseline-base-gnc-uniform": ("base", "gnc", True),
}


def _ate(setup, trajs: dict[int, np.ndarray], stamps: dict[int, np.ndarray], linked: list[int] | None = None) -> dict:
    """Per-robot ATE (each aligned alone) and merged ATE (one SE(3) alignment for all), RMSE in metres; with
    `linked` (the robots joined by loop closures), also the merged ATE of those robots alone."""
    from swarmsplat.slam.metrics import ate_multi

    gt, est = {}, {}
    for r, seq in enumerate(setup.dataset.agents):
        if r not in trajs or not len(trajs[r]) or seq.gt_poses is None:
            continue
        frames = frames_of(seq, stamps[r])[: len(trajs[r])]  # keyframes skipped as unreadable leave gaps
        gt[seq.name] = (np.asarray(stamps[r])[: len(frames)], seq.gt_poses[frames])
        est[seq.name] = (np.asarray(stamps[r]), trajs[r])
    if not est:
        return {}
    try:
        res = ate_multi(gt, est, align="se3", by_index=True)
    except InputError as e:  # too few keyframes to align (a run interrupted early)
        return {"note": f"not aligned: {e}"}
    out = {"merged_rmse": res.joint.rmse, "per_robot_rmse": {k: v.rmse for k, v in res.per_agent.items()},
           "_result": res}
    names = [setup.dataset.agents[r].name for r in (linked or [])]
    if len(names) >= 2 and all(n in est for n in names):
        sub = ate_multi({n: gt[n] for n in names}, {n: est[n] for n in names}, align="se3", by_index=True)
        out["linked_robots"] = names
        out["linked_merged_rmse"] = sub.joint.rmse
    return out


def frames_of(seq, stamps) -> np.ndarray:
    """Frame indices of `seq` whose timestamps are `stamps` (a robot's keyframes, in order)."""
    t = np.asarray(seq.timestamps, dtype=np.float64)
    i = np.clip(np.searchsorted(t, np.asarray(stamps, dtype=np.float64)), 0, max(len(t) - 1, 0))
    prev = np.clip(i - 1, 0, None)
    return np.where(np.abs(t[prev] - stamps) < np.abs(t[i] - stamps), prev, i)


def linked_robots(graph) -> list[int]:
    """The largest set of robots joined by inter-robot loop closures in `graph` (ties: the lowest ids)."""
    from swarmsplat.graph.pose_graph import key_robot

    parent: dict[str, str] = {}

    def find(x):
        parent.setdefault(x, x)
        while parent[x] != x:
            x = parent[x]
        return x

    for e in graph.loops():
        a, b = find(key_robot(e.key_i)), find(key_robot(e.key_j))
        if a != b:
            parent[max(a, b)] = min(a, b)
    groups: dict[str, list[str]] = {}
    for r in parent:
        groups.setdefault(find(r), []).append(r)
    best = max(groups.values(), key=lambda g: (len(g), [-ord(c) for c in sorted(g)]), default=[])
    return sorted(ord(c) - ord("a") for c in best)


def _public(d: dict) -> dict:
    return {k: v for k, v in d.items() if not k.startswith("_")}


def write_outputs(out: Path, setup, robots: dict[int, dict], final_subs: dict, *, mode: str,
                  status: str = "complete", reason: str | None = None, skipped: list | None = None) -> dict:
    """robots: id -> {trajectory, odometry, timestamps, bytes, estimate, n_solves, end}; final_subs: the graphs of
    the optimiser's last solve (robot id -> GraphSubmission), re-solved here for the comparison and the g2o.
    status: "complete", or "interrupted" / "failed" (with `reason`) for a run cut short, which skips the other
    formulations' re-solves and the plot; skipped: {"agent", "frame", "reason"} of unreadable keyframes."""
    from swarmsplat.graph.g2o import write_g2o
    from swarmsplat.slam.io.trajectory import write_tum

    out = Path(out)
    names = {r: s.name for r, s in enumerate(setup.dataset.agents)}
    if getattr(setup, "config", None) is not None:
        atomic_write_text(out / "config.yaml", setup.config.to_yaml())
    (out / "odometry").mkdir(parents=True, exist_ok=True)
    for r, d in robots.items():
        if not len(d["timestamps"]):  # no keyframe yet (a run interrupted early)
            continue
        write_tum(out / f"{names[r]}.txt", d["timestamps"], d["trajectory"])
        write_tum(out / "odometry" / f"{names[r]}.txt", d["timestamps"], d["odometry"])
    stamps = {r: d["timestamps"] for r, d in robots.items()}
    cfg = setup.node_config.solve
    distributed = cfg.solver == "distributed"  # final_subs: every robot's own graph; the reference solve is LM
    sol = solve_group(final_subs, replace(cfg, solver="lm") if distributed else cfg) if final_subs else None
    linked = linked_robots(sol.graph) if sol else []
    run = _ate(setup, {r: d["trajectory"] for r, d in robots.items()}, stamps, linked)
    odo = _ate(setup, {r: d["odometry"] for r, d in robots.items()}, stamps, linked)
    complete = status == "complete"
    metrics = {"status": status, **({"reason": reason} if reason else {}), "skipped_frames": list(skipped or []),
               "mode": mode, "formulation": cfg.formulation, "solver": cfg.solver, "uniform_noise": cfg.uniform_noise,
               "schedule": setup.schedule.to_dict(), "stride": setup.stride,
               "ate": _public(run), "odometry_only_ate": _public(odo), "alternatives": {}}
    if sol is not None:
        keys = sorted(sol.graph.poses)
        from swarmsplat.graph.pose_graph import robot_key

        poses = {}
        off = 0
        for r, c in zip(sol.robots, sol.counts):
            for i in range(c):
                poses[robot_key(chr(ord("a") + r), i)] = robots[r]["trajectory"][i] if distributed else \
                    sol.poses[off + i]
            off += c
        if distributed:
            metrics["distributed"] = distributed_metrics(sol, poses, robots, cfg.formulation)
        write_g2o(sol.graph, out / "pose_graph_optimized.g2o", {k: poses[k] for k in keys})
        loops = sol.graph.loops()
        metrics["loop_closures"] = {"count": len(loops),
                                    "per_pair": _per_pair(loops), "mean_confidence": float(np.mean(
                                        [e.confidence for e in loops])) if loops else None}
        for name, (f, s, u) in (ALTERNATIVES if complete else {}).items():
            alt = solve_group(final_subs, replace(setup.node_config.solve, formulation=f, solver=s, uniform_noise=u))
            trajs, off = {}, 0
            for r, c in zip(alt.robots, alt.counts):
                trajs[r] = alt.poses[off: off + c]
                off += c
            metrics["alternatives"][name] = {**_public(_ate(setup, trajs, {r: stamps[r][: len(trajs[r])]
                                                                           for r in trajs}, linked)),
                                             "time_s": alt.time_s}
    metrics["bytes"] = {names[r]: d["bytes"] for r, d in robots.items()}
    if complete:  # reads every keyframe image again: not while the user waits for an interrupted run to end
        metrics["images_bytes"] = {names[r]: _image_bytes(setup, r, d["timestamps"]) for r, d in robots.items()}
    metrics["n_solves"] = {names[r]: d["n_solves"] for r, d in robots.items()}
    metrics["estimate_stamp"] = {names[r]: (list(d["estimate"].stamp) if d["estimate"] is not None else None)
                                 for r, d in robots.items()}
    metrics["end"] = {names[r]: d.get("end") for r, d in robots.items()}
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2, default=float))
    if complete and run.get("_result") is not None:
        _plot(out / "trajectories.png", run["_result"])
    return metrics


def distributed_metrics(sol, poses: dict, robots: dict[int, dict], formulation: str) -> dict:
    """The distributed solve against the centralised one of the same final graph (`sol`, LM): the team's cost at
    the robots' poses and loop scales (`final_error`, the centralised problem's objective), the centralised cost,
    their ratio, each robot's steps and the bytes of the distributed estimates sent."""
    from swarmsplat.graph.distributed.team import problem_error
    from swarmsplat.graph.formulations import build_problem

    from swarmsplat.slam.flocc.swarm.optimiser import initial_poses

    g = sol.graph
    held = {k: s for d in robots.values() for k, s in (d.get("loop_scales") or {}).items()}
    scales = {n: held.get((e.key_i, e.key_j), e.odom_scale or 1.0) for n, e in enumerate(g.edges) if e.up_to_scale}
    problem = build_problem(g, formulation, "odometry", initial_poses=initial_poses(g))
    central = sol.final_error
    final = problem_error(problem, poses, scales, {})
    return {"final_error": final, "central_error": central, "ratio": final / central if central > 0 else None,
            "steps": {str(r): d.get("steps", 0) for r, d in robots.items()},
            "bytes_total": int(sum(d["bytes"].get("sent_bytes", {}).get("DistributedEstimate", 0)
                                   for d in robots.values()))}


def _per_pair(loops) -> dict:
    from swarmsplat.graph.pose_graph import key_robot

    out: dict[str, int] = {}
    for e in loops:
        k = f"{key_robot(e.key_i)}-{key_robot(e.key_j)}"
        out[k] = out.get(k, 0) + 1
    return out


def _image_bytes(setup, robot: int, stamps: np.ndarray) -> dict:
    """What sending the keyframe images themselves would cost once: raw RGB and PNG-compressed."""
    import cv2

    seq = setup.dataset.agents[robot]
    frames = frames_of(seq, stamps) if len(stamps) else []
    raw = png = 0
    for f in frames:
        im = seq[int(f)].color
        raw += im.nbytes
        png += len(cv2.imencode(".png", im[..., ::-1])[1])
    return {"raw": int(raw), "png": int(png), "keyframes": len(frames)}


def _plot(path: Path, res) -> None:
    from swarmsplat.slam.io.plots import plot_trajectories

    S = res.joint.transform
    est = {k: S.apply_to_poses(v.pairs.T_est)[:, :3, 3] for k, v in res.per_agent.items()}
    gt = {k: v.pairs.T_gt[:, :3, 3] for k, v in res.per_agent.items()}
    plot_trajectories(path, gt, est, title=f"swarm: merged ATE RMSE {res.joint.rmse:.3f} m (one SE(3) alignment)")
