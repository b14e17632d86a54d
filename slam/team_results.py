"""Everything a team run writes, side by side in one folder:

  config.yaml, server.yaml                 the settings actually used (agent pipeline; server role)
  trajectories/<agent>.txt                 TUM, with loop closures, in the agent's component frame
  trajectories_no_lc/<agent>.txt           TUM, tracking only, in the agent's own frame
  pose_graph_initial.g2o                   keyframe graph at the tracking-only poses (joined frames applied)
  pose_graph_optimized.g2o                 the same graph after the final optimisation
  map.ply                                  merged 3DGS map of agent 0's component (the global frame)
  map_<agent>.ply                          one per other component (agents never linked to agent 0)
  loops.csv                                every loop candidate with the reason for its outcome
  trajectory.png, trajectory_no_lc.png, renders.png, metrics.json, report.md
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from kernels.fileio import atomic_write_text

from .jsonio import write_json
from .loop_log import summarise, write_loops_csv


def write_team_results(team, ds, out: Path, *, wall_s: float, cpu_s: float, render_views: int = 8,
                       progress: bool = False, run_info: dict | None = None) -> dict:
    from graph.g2o import write_g2o

    from .ply import save_ply
    from .report import write_report
    from .trajectory import write_tum

    t_eval = time.perf_counter()
    srv = team.server
    names = [ag.name for ag in team.agents]
    atomic_write_text(out / "config.yaml", team.cfg.to_yaml())
    atomic_write_text(out / "server.yaml", yaml.safe_dump(srv.cfg.model_dump(mode="json"), sort_keys=False))
    est, est_no_lc = {}, {}
    for a, name in enumerate(names):
        est[name], est_no_lc[name] = team.trajectory(a), team.trajectory_no_lc(a)
        if len(est[name][0]):
            write_tum(out / "trajectories" / f"{name}.txt", *est[name])
            write_tum(out / "trajectories_no_lc" / f"{name}.txt", *est_no_lc[name])

    g, _ = srv.build_graph()
    initial = {srv.key(a, kf.id): srv.slots[a].T_global_world @ team.keyframe_pose_no_lc(a, kf)
               for a, ag in enumerate(team.agents) for kf in ag.keyframes}
    optimised = srv.last_graph[1] if srv.last_graph and set(srv.last_graph[1]) == set(g.poses) else g.poses
    if g.poses:
        write_g2o(g, out / "pose_graph_initial.g2o", initial)
        write_g2o(g, out / "pose_graph_optimized.g2o", optimised)

    comps = srv.components()
    map_files = {}
    for root, members in comps.items():
        fname = "map.ply" if root == 0 else f"map_{names[root]}.ply"
        save_ply(out / fname, srv.merged_map(root))
        map_files[fname] = [names[m] for m in members]

    write_loops_csv(out / "loops.csv", srv.records)
    traj = _trajectory_metrics(team, ds, est, est_no_lc, out)
    if progress:
        print("[team] rendering evaluation views from the merged map", file=sys.stderr)
    render = _render_metrics(team, ds, out, render_views)
    agents = []
    for a, (ag, seq) in enumerate(zip(team.agents, ds.agents)):
        t = ag.time
        agents.append({
            "name": ag.name, "frames": len(seq), "frames_tracked": len(ag.poses), "skipped_frames": list(t.skipped),
            "keyframes": len(ag.keyframes), "submaps": len(ag.gmap.submaps), "gaussians": len(ag.gmap),
            "component": names[srv.slots[a].component], "in_global_frame": srv.slots[a].component == 0,
            **traj["agents"][a], **render["agents"][a],
            "time_s": {"tracking": t.tracking, "mapping": t.mapping},
        })
    summary = summarise(srv.records)
    metrics = {
        "dataset": str(ds.root), "dataset_name": ds.name, "agents": agents,
        "ate_rmse_team": traj["team"], "psnr": render["psnr"], "ssim": render["ssim"],
        "depth_l1": render["depth_l1"], "render_views": render["views"],
        "components": {names[r]: [names[m] for m in ms] for r, ms in comps.items()}, "maps": map_files,
        "gaussians": sum(len(ag.gmap) for ag in team.agents),
        "loops": summary, "loops_accepted": summary["intra"]["accepted"] + summary["inter"]["accepted"],
        "loop_candidates": len(srv.records), "pose_graph_optimisations": srv.optimisations,
        "time_s": {"wall": wall_s, "cpu": cpu_s, "server": dict(srv.time),
                   "evaluation": time.perf_counter() - t_eval},
        "kernels": team.cfg.kernels.model_dump(), "run": run_info or {},
    }
    metrics["time_s"]["evaluation"] = time.perf_counter() - t_eval
    write_json(out / "metrics.json", metrics)
    write_report(out, metrics)
    return metrics


def _gt(seq):
    gt = seq.gt_poses
    if gt is None:
        return None
    ok = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
    return (seq.timestamps[ok], gt[ok]) if ok.any() else None


def _trajectory_metrics(team, ds, est: dict, est_no_lc: dict, out: Path) -> dict:
    """Per-agent ATE (own SE(3) alignment) with and without loops, and the team ATE of agent 0's component
    under ONE alignment (what the merged map's consistency rests on)."""
    from .metrics import ate, ate_multi
    from .plots import plot_trajectories

    names = [ag.name for ag in team.agents]
    per, gt_pos, est_pos, errs, nolc_pos, nolc_err = [], {}, {}, {}, {}, {}
    for a, (name, seq) in enumerate(zip(names, ds.agents)):
        gt = _gt(seq)
        if gt is None or not len(est[name][0]):
            per.append({"ate_rmse": None, "ate_rmse_no_lc": None})
            continue
        r = ate(*gt, *est[name], align="se3", max_diff=0.01)
        r0 = ate(*gt, *est_no_lc[name], align="se3", max_diff=0.01)
        per.append({"ate_rmse": r.rmse, "ate_rmse_no_lc": r0.rmse, "ate_matched": r.matched})
        gt_pos[name], est_pos[name], errs[name] = r.pairs.T_gt[:, :3, 3], r.T_est_aligned[:, :3, 3], r.errors
        nolc_pos[name], nolc_err[name] = r0.T_est_aligned[:, :3, 3], r0.errors
    members = [names[a] for a in team.server.components().get(0, []) if names[a] in gt_pos]
    team_rmse = None
    if members:
        j = ate_multi({n: _gt(ds.agents[names.index(n)]) for n in members}, {n: est[n] for n in members},
                      align="se3", max_diff=0.01)
        team_rmse = j.joint.rmse
        S = j.joint.transform
        for n in members:  # one alignment for the whole global frame
            T = S.apply_to_poses(j.per_agent[n].pairs.T_est)
            est_pos[n] = T[:, :3, 3]
            errs[n] = np.linalg.norm(est_pos[n] - j.per_agent[n].pairs.T_gt[:, :3, 3], axis=1)
    if gt_pos:
        title = (f"with loop closures: global-frame ATE {100 * team_rmse:.2f} cm (one alignment)"
                 if team_rmse is not None else "with loop closures")
        plot_trajectories(out / "trajectory.png", gt_pos, est_pos, errors=errs, title=title)
        plot_trajectories(out / "trajectory_no_lc.png", gt_pos, nolc_pos, errors=nolc_err,
                          title="tracking only (each agent aligned on its own)")
    return {"agents": per, "team": team_rmse}


def _eval_keyframes(ag, n: int) -> list:
    kfs = ag.keyframes
    if n <= 0 or len(kfs) <= n:
        return list(kfs)
    return [kfs[i] for i in np.unique(np.linspace(0, len(kfs) - 1, n).round().astype(int))]


def _render_metrics(team, ds, out: Path, views: int) -> dict:
    """Merged-map rendering quality: chosen keyframes of every agent rendered from the merged map of its
    component at the keyframe's optimised pose, at the mapping resolution, against the input frame."""
    from .frames import make_rgbd
    from .metrics import depth_l1, psnr, ssim
    from .render import render, viewmat_from_pose

    srv, cfg = team.server, team.cfg
    maps = {root: srv.merged_map(root) for root in srv.components()}
    per, all_p, all_s, all_d, grid = [], [], [], [], []
    for a, (ag, seq) in enumerate(zip(team.agents, ds.agents)):
        ps, ss, dl = [], [], []
        params = maps[srv.slots[a].component]
        for kf in _eval_keyframes(ag, views):
            f = seq[kf.frame_index]
            ref = make_rgbd(f.color, f.depth, seq.camera, min_depth=cfg.image.min_depth, max_depth=cfg.image.max_depth)
            ref = ref.resized(cfg.image.max_width).resized(cfg.mapping.max_width)
            with torch.no_grad():
                o = render(params, viewmat_from_pose(srv.global_pose(a, kf)), ref.camera)
            color = o.color.clamp(0, 1)
            gt_c = ref.color_tensor()
            ps.append(psnr(color.permute(2, 0, 1), gt_c.permute(2, 0, 1)))
            ss.append(ssim(color.permute(2, 0, 1), gt_c.permute(2, 0, 1)))
            if (ref.depth > 0).any():
                dl.append(depth_l1(o.depth, torch.as_tensor(ref.depth)))
            if len(grid) < 3 * (a + 1):
                grid.append((f"{ag.name} frame {kf.frame_index}", ref.color, (color.numpy() * 255).astype(np.uint8)))
        per.append({"psnr": _mean(ps), "ssim": _mean(ss), "depth_l1": _mean(dl), "render_views": len(ps)})
        all_p += ps
        all_s += ss
        all_d += dl
    if grid:
        _render_grid(out / "renders.png", grid)
    return {"agents": per, "psnr": _mean(all_p), "ssim": _mean(all_s), "depth_l1": _mean(all_d), "views": len(all_p)}


def _render_grid(path: Path, rows: list) -> None:
    """PNG grid: one row per view, real frame left, merged-map render right."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from kernels.fileio import atomic_path

    fig = Figure(figsize=(6.4, 2.4 * len(rows)))
    FigureCanvasAgg(fig)
    for i, (label, real, rendered) in enumerate(rows):
        for j, (img, what) in enumerate(((real, "input"), (rendered, "merged-map render"))):
            ax = fig.add_subplot(len(rows), 2, 2 * i + j + 1)
            ax.imshow(img)
            ax.set_axis_off()
            ax.set_title(f"{label}: {what}", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)


def _mean(v: list) -> float | None:
    v = [x for x in v if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else None
