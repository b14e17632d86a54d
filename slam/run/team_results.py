"""Everything a team run writes, side by side in one folder:

  config.yaml, server.yaml                 the settings actually used (agent pipeline; server role)
  trajectories/<agent>.txt                 TUM, with loop closures, in the agent's component frame
  trajectories_no_lc/<agent>.txt           TUM, tracking only, in the agent's own frame
  pose_graph_initial.g2o                   keyframe graph at the tracking-only poses (joined frames applied)
  pose_graph_optimized.g2o                 the same graph after the final optimisation
  map.ply                                  merged 3DGS map of agent 0's component (the global frame), after the
                                           server's global refinement (config map_refine) when it is on
  map_<agent>.ply                          one per other component (agents never linked to agent 0)
  loops.csv                                every loop candidate with the reason for its outcome
  trajectory.png, trajectory_no_lc.png, renders.png, metrics.json, report.md
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import yaml

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_write_text

from swarmsplat.slam.io.jsonio import write_json
from swarmsplat.slam.dense.loops.loop_log import summarise, write_loops_csv
from swarmsplat.slam.metrics.views import exposure_record
from .runtime import check_not_empty, guard_warnings, kernels_record


def write_team_results(team, ds, out: Path, *, wall_s: float, cpu_s: float, render_views: int = 8,
                       progress: bool = False, run_info: dict | None = None, before_refine: dict | None = None,
                       refine: dict | None = None) -> dict:
    """Write everything listed in the module docstring; returns the metrics. before_refine: render_metrics of
    the merged map before the server's global refinement (None when it was off); refine: its per-component
    statistics (Server.refine_maps)."""
    from swarmsplat.graph.g2o import write_g2o

    from swarmsplat.slam.dense.ply import save_ply
    from .report import write_report
    from swarmsplat.slam.io.trajectory import write_tum

    check_not_empty(team.agents)
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
        save_ply(out / fname, srv.display_map(root), max_color=None)
        map_files[fname] = [names[m] for m in members]

    write_loops_csv(out / "loops.csv", srv.records)
    traj = _trajectory_metrics(team, ds, est, est_no_lc, out)
    traj_before = (before_refine or {}).get("trajectories")
    if traj_before is not None:  # the same scores at the poses before the refinement refined the keyframes
        tb = _trajectory_metrics(team, ds, dict(zip(names, traj_before)), est_no_lc, None)
        traj["team_before_refine"] = tb["team"]
        for entry, e in zip(traj["agents"], tb["agents"]):
            entry["ate_rmse_before_refine"] = e["ate_rmse"]
    if progress:
        print("[team] rendering evaluation views from the merged map", file=sys.stderr)
    render = render_metrics(team, ds, render_views)
    grid = render.pop("grid")
    if grid:
        _render_grid(out / "renders.png", grid)
    before = dict(before_refine or {})
    before.pop("grid", None)
    before.pop("trajectories", None)
    agents = []
    for a, (ag, seq) in enumerate(zip(team.agents, ds.agents)):
        t = ag.time
        agents.append({
            "name": ag.name, "frames": len(seq), "frames_tracked": len(ag.poses), "skipped_frames": ag.skipped_frames(),
            "keyframes": len(ag.keyframes), "submaps": len(ag.gmap.submaps), "gaussians": len(ag.gmap),
            "component": names[srv.slots[a].component], "in_global_frame": srv.slots[a].component == 0,
            **traj["agents"][a], **render["agents"][a],
            "psnr_before_refine": before["agents"][a]["psnr"] if before else None,
            # own submaps as mapping left them: the refinement's overlap cull leaves each submap its owned
            # surfaces only, so they are scored before it when it runs
            "psnr_submaps": (before or render)["agents"][a].get("psnr_submaps"),
            "exposure": {**exposure_record(ag.keyframes), "model_from_keyframe": getattr(ag, "exposure_from", None)},
            "time_s": {"tracking": t.tracking, "mapping": t.mapping},
        })
    summary = summarise(srv.records)
    metrics = {
        "status": "complete",
        "dataset": str(ds.root), "dataset_name": ds.name, "agents": agents,
        "ate_rmse_team": traj["team"], "ate_rmse_team_agents": traj["team_agents"],
        "ate_rmse_team_before_refine": traj.get("team_before_refine"),
        "joined_agents": [names[a] for a in comps.get(0, [])],
        "unjoined_agents": [names[a] for a in range(len(names)) if srv.slots[a].component != 0],
        "all_agents_joined": all(srv.slots[a].component == 0 for a in range(len(names))),
        "psnr": render["psnr"], "ssim": render["ssim"],
        "depth_l1": render["depth_l1"], "render_views": render["views"],
        # the same keyframes from their own submaps alone: the merged map's loss against it is the merge's cost
        "psnr_submaps": (before or render).get("psnr_submaps"), "psnr_raw": render.get("psnr_raw"),
        "psnr_novel_raw": render.get("psnr_novel_raw"),
        "psnr_novel": render["psnr_novel"], "ssim_novel": render["ssim_novel"], "novel_views": render["novel_views"],
        "psnr_before_refine": before.get("psnr"), "ssim_before_refine": before.get("ssim"),
        "render_resolution": render["resolution"], "input_resolution": render["input_resolution"],
        **{k: render[k] for k in ("psnr_input_resolution", "ssim_input_resolution", "depth_l1_input_resolution",
                                  "psnr_novel_input_resolution", "ssim_novel_input_resolution")},
        "map_refine": {"config": team.cfg.map_refine.model_dump(), "components": refine or {},
                       "evaluation_before_s": before.get("seconds")},
        "components": {names[r]: [names[m] for m in ms] for r, ms in comps.items()}, "maps": map_files,
        "gaussians": sum(len(ag.gmap) for ag in team.agents),
        "loops": summary, "loops_accepted": summary["intra"]["accepted"] + summary["inter"]["accepted"],
        "loop_candidates": len(srv.records), "pose_graph_optimisations": srv.optimisations,
        "pose_graph_not_applied": srv.not_applied,
        "inter_verify_s": srv.time["inter"],
        "joins": {"made": srv.joins, "undone": srv.joins_undone, "unconfirmed_loops": len(srv.pending),
                  "min_loops": srv.cfg.join_min_loops},
        "verification_budget": {"descriptor_per_keyframe": srv.cfg.top_k, "tau_sim": srv.cfg.tau_sim,
                                "pose_per_keyframe": team.cfg.loop_closure.pose_top_k
                                if team.cfg.loop_closure.candidates != "descriptor" else 0,
                                "intra": team.agents[0].loops.budget()},
        "inter_verify": {"by_source_and_coarse": srv.inter_stats, "coarse": srv.cfg.coarse,
                         "descriptor": srv.cfg.descriptor,
                         "encoder": srv.encoder.stats() if srv.encoder is not None else None,
                         "cloud_route": cloud_route_stats(srv)},
        "time_s": {"wall": wall_s, "cpu": cpu_s, "server": dict(srv.time),
                   "evaluation": time.perf_counter() - t_eval},
        "kernels": kernels_record(team.cfg.kernels), "run": run_info or {},
        **guard_warnings(team.agents),
    }
    metrics["time_s"]["evaluation"] = time.perf_counter() - t_eval
    write_json(out / "metrics.json", metrics)
    write_report(out, metrics)
    return metrics


def cloud_route_stats(srv) -> dict:
    """The cloud route's cost and outcome: windows built, registrations, seconds, and per query keyframe."""
    from swarmsplat.slam.dense.loops.local_clouds import WindowRegistrar

    st = (srv.clouds or WindowRegistrar()).stats()
    tried = len(srv.cloud_tries)
    out = {"enabled": srv.cfg.cloud_route, "method": srv.cfg.cloud_method, "render_check": srv.cfg.render_check,
           **st, "query_keyframes": tried,
           "seconds_per_query_keyframe": (st["prepare_s"] + st["register_s"]) / tried if tried else 0.0}
    for kind in ("inter", "intra"):  # every candidate that took the route, and how it ended
        rs = [r for r in srv.records if r.route == "cloud" and r.kind == kind]
        out[kind] = {"candidates": len(rs), "accepted": sum(r.accepted for r in rs),
                     "passed_render": sum(r.render_agree == r.render_agree and r.reason_code != "render" for r in rs),
                     "rejected_render": sum(r.reason_code == "render" for r in rs)}
    out["intra_agents"] = {ag.name: ag.loops.cloud_stats() for ag in (s.agent for s in srv.slots)}
    return out


def _gt(seq):
    gt = seq.gt_poses
    if gt is None:
        return None
    ok = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
    return (seq.timestamps[ok], gt[ok]) if ok.any() else None


def _trajectory_metrics(team, ds, est: dict, est_no_lc: dict, out: Path | None) -> dict:
    """Per-agent ATE (own SE(3) alignment) with and without loops, and the team ATE of agent 0's component
    under ONE alignment (what the merged map's consistency rests on). out None: no plots."""
    from swarmsplat.slam.metrics import ate, ate_multi
    from swarmsplat.slam.io.plots import plot_trajectories

    names = [ag.name for ag in team.agents]
    per, gt_pos, est_pos, errs, nolc_pos, nolc_err, has_gt = [], {}, {}, {}, {}, {}, []
    for a, (name, seq) in enumerate(zip(names, ds.agents)):
        gt = _gt(seq)
        if gt is None or not len(est[name][0]):
            per.append({"ate_rmse": None, "ate_rmse_no_lc": None})
            continue
        has_gt.append(name)
        try:
            r = ate(*gt, *est[name], align="se3", max_diff=0.01)
            r0 = ate(*gt, *est_no_lc[name], align="se3", max_diff=0.01)
        except InputError as e:  # too few / collinear poses to align this agent on its own
            per.append({"ate_rmse": None, "ate_rmse_no_lc": None, "ate_note": f"not aligned on its own: {e}"})
            continue
        per.append({"ate_rmse": r.rmse, "ate_rmse_no_lc": r0.rmse, "ate_matched": r.matched})
        gt_pos[name], est_pos[name], errs[name] = r.pairs.T_gt[:, :3, 3], r.T_est_aligned[:, :3, 3], r.errors
        nolc_pos[name], nolc_err[name] = r0.T_est_aligned[:, :3, 3], r0.errors
    members = [names[a] for a in team.server.components().get(0, []) if names[a] in has_gt]
    team_rmse = None
    if members:
        j = ate_multi({n: _gt(ds.agents[names.index(n)]) for n in members}, {n: est[n] for n in members},
                      align="se3", max_diff=0.01)
        team_rmse = j.joint.rmse
        S = j.joint.transform
        for n in members:  # one alignment for the whole global frame
            T = S.apply_to_poses(j.per_agent[n].pairs.T_est)
            est_pos[n], gt_pos[n] = T[:, :3, 3], j.per_agent[n].pairs.T_gt[:, :3, 3]
            errs[n] = np.linalg.norm(est_pos[n] - gt_pos[n], axis=1)
            entry = per[names.index(n)]
            if entry["ate_rmse"] is None:  # scored under the team's one alignment instead
                entry.update(ate_rmse=j.per_agent[n].rmse, ate_matched=j.per_agent[n].matched, ate_align="joint")
    if gt_pos and out is not None:
        title = (f"with loop closures: global-frame ATE {100 * team_rmse:.2f} cm (one alignment)"
                 if team_rmse is not None else "with loop closures")
        plot_trajectories(out / "trajectory.png", gt_pos, est_pos, errors=errs, title=title)
        plot_trajectories(out / "trajectory_no_lc.png", {n: gt_pos[n] for n in nolc_pos}, nolc_pos, errors=nolc_err,
                          title="tracking only (each agent aligned on its own)")
    return {"agents": per, "team": team_rmse, "team_agents": members if team_rmse is not None else []}


def _spread(items: list, n: int) -> list:
    """At most n of `items`, evenly spread (all when n <= 0 or there are fewer)."""
    if n <= 0 or len(items) <= n:
        return list(items)
    return [items[i] for i in np.unique(np.linspace(0, len(items) - 1, n).round().astype(int))]


def render_metrics(team, ds, views: int, *, novel: bool = True) -> dict:
    """Merged-map rendering quality at the working resolution (cfg.image.max_width, against the input frame
    brought to it the way the pipeline does: area downsampling, no blur) and at the input resolution
    (slam.metrics.views), colour clamped to [0, 1].

    Training views: `views` keyframes per agent (evenly spread), rendered from the merged map of the agent's
    component at the keyframe's optimised pose. Held-out views (`novel`): `views` tracked frames per agent that
    are NOT keyframes — no mapping or refinement step ever saw them — at their pose with loop closures.
    Returns {"agents": [...], "psnr", "ssim", "depth_l1", "views", "psnr_novel", "ssim_novel", "novel_views",
    the same with the suffix _input_resolution, "resolution" (working [w, h]), "input_resolution" [w, h], "grid"}
    (grid: rows for renders.png)."""
    from swarmsplat.slam.metrics.views import INPUT, held_out_exposure, mean_scores, resolutions, score_view

    from swarmsplat.slam.dense.mapping.exposure import display_gain

    srv, cfg = team.server, team.cfg
    comps = srv.components()
    maps = {root: srv.merged_map(root) for root in comps}
    shown = {root: display_gain(srv.keyframes_of(root)) for root in comps}
    per, grid, res = [], [], {}
    acc = {"kf": [], "novel": []}

    def score(params, T, seq, index, exposure):
        f = seq[index]
        return score_view(params, T, f.color, f.depth, seq.camera, cfg, exposure=exposure, display=display)

    for a, (ag, seq) in enumerate(zip(team.agents, ds.agents)):
        params = maps[srv.slots[a].component]
        display = shown[srv.slots[a].component]
        kfs, novel_s = [], []
        for kf in _spread(ag.keyframes, views):
            s, ref, color = score(params, srv.global_pose(a, kf), seq, kf.frame_index, kf.exposure)
            own = ag.gmap.submaps[kf.submap_id]  # the same view from its own submap alone: what the merge costs
            if len(own):
                s["psnr_submaps"] = score(own.params, kf.T_local, seq, kf.frame_index, kf.exposure)[0]["psnr"]
            kfs.append(s)
            res = resolutions(seq.camera, cfg)
            if len(grid) < 3 * (a + 1):
                grid.append((f"{ag.name} frame {kf.frame_index}", ref.color, (color.numpy() * 255).astype(np.uint8)))
        if novel and ag.poses:
            kf_frames = {kf.frame_index for kf in ag.keyframes}
            _, T_all = srv.global_trajectory(a)
            held = [(rec.frame_index, T_all[i]) for i, rec in enumerate(ag.poses) if rec.frame_index not in kf_frames]
            for index, T in _spread(held, views):
                s, _, _ = score(params, T, seq, index, held_out_exposure(ag.keyframes, index))
                novel_s.append({k: s.get(k) for k in ("psnr", "ssim", "psnr" + INPUT, "ssim" + INPUT, "psnr_raw")})
        m, mn = mean_scores(kfs), mean_scores(novel_s)
        per.append({**_render_keys(m, mn), "render_views": len(kfs), "novel_views": len(novel_s)})
        acc["kf"] += kfs
        acc["novel"] += novel_s
    m, mn = mean_scores(acc["kf"]), mean_scores(acc["novel"])
    return {"agents": per, **_render_keys(m, mn), "views": len(acc["kf"]), "novel_views": len(acc["novel"]),
            "resolution": res.get("render_resolution"), "input_resolution": res.get("input_resolution"),
            "grid": grid}


def _render_keys(m: dict, mn: dict) -> dict:
    """metrics.json keys of one set of training-view scores `m` and held-out scores `mn` (slam.metrics.views)."""
    from swarmsplat.slam.metrics.views import INPUT

    out = {k: m.get(k) for k in ("psnr", "ssim", "depth_l1")}
    out.update(psnr_submaps=m.get("psnr_submaps"), psnr_novel=mn.get("psnr"), ssim_novel=mn.get("ssim"))
    if m.get("psnr_raw") is not None:  # the same views without the keyframes' exposures (slam.metrics.views)
        out.update(psnr_raw=m.get("psnr_raw"), psnr_novel_raw=mn.get("psnr_raw"))
    out.update({k + INPUT: m.get(k + INPUT) for k in ("psnr", "ssim", "depth_l1")})
    out.update(psnr_novel_input_resolution=mn.get("psnr" + INPUT), ssim_novel_input_resolution=mn.get("ssim" + INPUT))
    return out


def _render_grid(path: Path, rows: list) -> None:
    """PNG grid: one row per view, real frame left, merged-map render right."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from swarmsplat.kernels.fileio import atomic_path

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
