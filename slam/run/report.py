"""The Markdown report of a team run (`report.md`), built from its metrics.json and the figures beside it:
per-agent ATE with and without loop closures (the shape of GRAND-SLAM's Table II), merged-map rendering quality
(Table V's shape: PSNR, SSIM, depth L1), trajectory plots, rendered-vs-real views, and a loop-closure summary
that says why candidates were rejected."""

from __future__ import annotations

from pathlib import Path

from swarmsplat.kernels.fileio import atomic_write_text

_REASONS = {
    "accepted": "accepted",
    "similarity": "descriptor similarity below τ_sim",
    "registration": "registration failed",
    "fitness": "ICP fitness ≤ τ_f",
    "rmse": "ICP inlier RMSE ≥ τ_ρ",
    "correction": "correction larger than max_correction",
    "gnc": "rejected by GNC (inconsistent)",
    "render": "the map rendered from the pose contradicts the view",
}


def _cm(x) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def _f(x, fmt: str) -> str:
    return "–" if x is None else format(x, fmt)


def render_report(m: dict, files: set[str] | None = None) -> str:
    """Markdown text for metrics dict `m` (as written to metrics.json); `files` names the figures present."""
    files = files or set()
    L = [f"# swarmsplat team run: {m.get('dataset_name') or Path(m.get('dataset', '')).name}", ""]
    ag = m["agents"]
    L += [f"{len(ag)} agents, {sum(a['frames_tracked'] for a in ag)} frames tracked, "
          f"{sum(a['keyframes'] for a in ag)} keyframes, {m['gaussians']} Gaussians; "
          f"{m['loops_accepted']} loop closures accepted of {m['loop_candidates']} candidates; "
          f"wall time {m['time_s']['wall']:.0f} s (CPU {m['time_s']['cpu']:.0f} s) plus "
          f"{m['time_s']['evaluation']:.0f} s evaluation.", ""]

    L += ["## Trajectory accuracy (ATE RMSE, cm)", "",
          "Each agent aligned to its ground truth on its own (SE(3)), as GRAND-SLAM's Table II. *Without* loop "
          "closures is the same run's tracking-only trajectory.", "",
          "| Agent | frames | keyframes | w/o loop closures | with loop closures | frame |",
          "|---|---:|---:|---:|---:|---|"]
    for a in ag:
        where = ("global" if a["in_global_frame"] else
                 "own" if a["component"] == a["name"] else f"{a['component']}'s")
        L.append(f"| {a['name']} | {a['frames_tracked']} | {a['keyframes']} | {_cm(a.get('ate_rmse_no_lc'))} | "
                 f"{_cm(a.get('ate_rmse'))} | {where} |")
    vals = [a for a in ag if a.get("ate_rmse") is not None and a.get("ate_rmse_no_lc") is not None]
    if vals:
        n0 = sum(a["ate_rmse_no_lc"] for a in vals) / len(vals)
        n1 = sum(a["ate_rmse"] for a in vals) / len(vals)
        L.append(f"| **mean** | | | {_cm(n0)} | {_cm(n1)} | |")
    if m.get("ate_rmse_team") is not None:
        over = m.get("ate_rmse_team_agents") or []
        left = m.get("unjoined_agents") or []
        L += ["", f"Team ATE of the agents in the global frame ({', '.join(over) or 'agent 0'}) under **one** "
                  f"alignment: **{_cm(m['ate_rmse_team'])} cm**."
              + (f" **Not joined** (own frame, not in this figure): {', '.join(left)}." if left else
                 " Every agent joined the global frame.")]
    elif m.get("unjoined_agents"):
        L += ["", f"No team ATE: not joined: {', '.join(m['unjoined_agents'])}."]
    L.append("")
    for fig, cap in (("trajectory.png", "With loop closures"), ("trajectory_no_lc.png", "Tracking only")):
        if fig in files:
            L += [f"![{cap}]({fig})", ""]

    res = m.get("render_resolution")
    at = f"{res[0]}x{res[1]}, the mapping resolution" if res else "the mapping resolution"
    ref = m.get("map_refine") or {}
    refined = m.get("psnr_before_refine") is not None
    L += ["## Rendering quality of the merged map", "",
          f"Rendered from the merged map of each agent's component at {at}, against the input frames (Table V's "
          "columns). *Keyframes* are training views, at their optimised pose; *held-out* frames are tracked frames "
          "that are not keyframes (no mapping or refinement step saw them), at their pose with loop closures."
          + (" *Before refinement* is the merged map straight after the final pose-graph optimisation, before the "
             "server's global map refinement (" + f"{ref.get('config', {}).get('iterations_per_keyframe')} steps "
             "per keyframe)." if refined else " Global map refinement was off."), "",
          "| Agent | keyframes | PSNR [dB] ↑ | SSIM ↑ | Depth L1 [cm] ↓ | PSNR before refinement | "
          "held-out frames | held-out PSNR | own submaps' PSNR |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for a in ag:
        L.append(f"| {a['name']} | {a.get('render_views', 0)} | {_f(a.get('psnr'), '.2f')} | "
                 f"{_f(a.get('ssim'), '.3f')} | {_cm(a.get('depth_l1'))} | {_f(a.get('psnr_before_refine'), '.2f')} | "
                 f"{a.get('novel_views', 0)} | {_f(a.get('psnr_novel'), '.2f')} | {_f(a.get('psnr_submaps'), '.2f')} |")
    L.append(f"| **all** | {m.get('render_views', 0)} | {_f(m.get('psnr'), '.2f')} | {_f(m.get('ssim'), '.3f')} | "
             f"{_cm(m.get('depth_l1'))} | {_f(m.get('psnr_before_refine'), '.2f')} | {m.get('novel_views', 0)} | "
             f"{_f(m.get('psnr_novel'), '.2f')} | {_f(m.get('psnr_submaps'), '.2f')} |")
    L.append("")
    L += ["*Own submaps' PSNR*: the same keyframes rendered from their own submap alone, as mapping left it "
          "(the merged map's loss against it is what the merge costs). Renders are scored as each camera saw the "
          "map: with the keyframe's exposure and white balance (`exposure` in metrics.json), a held-out frame with "
          "the exposure interpolated from the keyframes around it.", ""]
    if "renders.png" in files:
        L += ["![input vs merged-map render](renders.png)", ""]

    L += _loop_section(m)
    L += ["## Maps", ""]
    for f, members in m.get("maps", {}).items():
        L.append(f"- `{f}`: {', '.join(members)}")
    L += ["", "## Time (s)", "", "| stage | seconds |", "|---|---:|"]
    for a in ag:
        L.append(f"| {a['name']} tracking / mapping | {a['time_s']['tracking']:.1f} / {a['time_s']['mapping']:.1f} |")
    for k, v in m["time_s"]["server"].items():
        L.append(f"| server {k} | {v:.1f} |")
    L += [f"| wall (run) | {m['time_s']['wall']:.1f} |", f"| CPU (run, all threads) | {m['time_s']['cpu']:.1f} |",
          f"| evaluation and outputs | {m['time_s']['evaluation']:.1f} |", ""]
    return "\n".join(L)


def _loop_section(m: dict) -> list[str]:
    L = ["## Loop closures", "", "| kind | candidates | accepted | rejected: reasons |", "|---|---:|---:|---|"]
    for kind, s in m["loops"].items():
        rej = ", ".join(f"{_REASONS.get(k, k)}: {v}" for k, v in s["by_reason"].items() if k != "accepted") or "–"
        L.append(f"| {kind}-agent | {s['candidates']} | {s['accepted']} | {rej} |")
    L.append("")
    comps = m.get("components", {})
    if len(comps) > 1:
        L.append("Agents in separate frames (never linked by an accepted inter-agent loop): "
                 + "; ".join(", ".join(v) for v in comps.values()) + ".")
    else:
        L.append("All agents were brought into one global frame.")
    budget, joins = m.get("verification_budget"), m.get("joins")
    if budget:
        gate = "no similarity gate" if budget["tau_sim"] is None else f"similarity >= {budget['tau_sim']}"
        L.append(f"Inter-agent verification budget: at most {budget['descriptor_per_keyframe']} descriptor and "
                 f"{budget['pose_per_keyframe']} pose candidates per keyframe ({gate}).")
    if joins:
        L.append(f"Joins need {joins['min_loops']} mutually consistent loop(s): {joins['made']} made, "
                 f"{joins['undone']} undone, {joins['unconfirmed_loops']} verified loop(s) left unconfirmed.")
    cloud = (m.get("inter_verify") or {}).get("cloud_route")
    if cloud and (cloud["inter"]["candidates"] or cloud["intra"]["candidates"]):
        L.append(f"Cloud route (local maps registered as point clouds, checked by rendering): "
                 f"{cloud['inter']['candidates']} inter-agent candidates ({cloud['inter']['accepted']} accepted, "
                 f"{cloud['inter']['rejected_render']} refused by the render check), "
                 f"{cloud['intra']['candidates']} intra-agent ({cloud['intra']['accepted']} accepted, "
                 f"{cloud['intra']['rejected_render']} refused by the render check); the server's registrations "
                 f"{cloud['seconds_per_query_keyframe']:.2f} s per query keyframe that took the route.")
    inter = m["loops"].get("inter", {})
    registered = sum(v for k, v in inter.get("by_reason", {}).items() if k != "similarity")
    if registered == 0:
        L.append("No inter-agent candidate reached registration: no pair of keyframes of different agents was "
                 "similar enough (see `loops.csv`, reason `similarity`).")
    elif inter.get("accepted", 0) == 0:
        L.append("Inter-agent candidates were found but none passed the gates; `loops.csv` has each one's "
                 "fitness, RMSE and reason.")
    L += ["", "Every candidate, with agent and keyframe ids, similarity, registration outcome, fitness, RMSE and the "
              "reason, is in `loops.csv`.", ""]
    return L


def write_report(out_dir: str | Path, metrics: dict) -> Path:
    out = Path(out_dir)
    files = {p.name for p in out.glob("*.png")}
    path = out / "report.md"
    atomic_write_text(path, render_report(metrics, files))
    return path
