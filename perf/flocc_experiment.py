"""FLOCC-SLAM's formulation study (Tables II and III) on a synthetic 6-robot team.

    python -m perf.flocc_experiment --json OUT.json [--md OUT.md] [--quick] [--odometry vio lio] [--no-gnc]

A team from `graph.synthetic.make_team` (6 robots x 583 m = 3.5 km, ~2,000 inter-robot loops known up to scale,
scale errors log-normal per 40 m cell + per-loop jitter, 2% outliers, confidence from drawn correspondence
ratios). Two odometry backbones as the paper's tables: `vio` (VINS-Mono-like: 5% per-robot scale error, larger
yaw drift) and `lio` (LIO-like: 0.2% scale error, small drift). For every scale initialisation (ground truth,
raw network scale = 1, eq. 6 odometry ratio) the initial poses come from a chordal initialisation with the loops
rescaled by that initial scale; then each formulation (base, IS, SS) is solved with LM and with GNC. ATE is the
mean ± std position error over all keyframes after one rigid alignment. Time is the solver's wall time on this
machine (single process; the machine may be shared).
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import numpy as np

ROWS = [("LM", "base", "lm"), ("GNC", "base", "gnc"), ("IS-LM", "is", "lm"), ("IS-GNC", "is", "gnc"),
        ("SS-LM", "ss", "lm"), ("SS-GNC", "ss", "gnc")]
INITS = [("GT scale", "gt"), ("Raw scale", "raw"), ("Odometry scale", "odometry")]
BACKBONES = {
    "vio": dict(odo_scale_error=0.05, odo_yaw_bias=0.0015, odo_sigma_rot=0.004, odo_sigma_trans=0.03),
    "lio": dict(odo_scale_error=0.002, odo_yaw_bias=0.0003, odo_sigma_rot=0.002, odo_sigma_trans=0.01),
}


def team_config(backbone: str, quick: bool, seed: int = 0):
    from swarmsplat.graph.synthetic import TeamConfig

    kw = dict(BACKBONES[backbone], seed=seed)
    if quick:
        kw.update(length_m=250.0, target_loops=600, grid_nodes=3)  # smaller city so every robot meets another
    return TeamConfig(**kw)


def scaled_initial_poses(graph, scales: dict[int, float]):
    """Chordal initialisation of `graph` with each up-to-scale loop's translation multiplied by its scale."""
    from swarmsplat.graph.init import chordal_initialization

    g = graph.with_poses(graph.poses)
    g.edges = [copy.copy(e) for e in graph.edges]
    for n, s in scales.items():
        g.edges[n].T_ij = g.edges[n].T_ij.copy()
        g.edges[n].T_ij[:3, 3] *= s
    return chordal_initialization(g)


def run_backbone(backbone: str, quick: bool, gnc: bool = True, seed: int = 0, log=print, config=None) -> dict:
    """All rows x scale initialisations for one odometry backbone; `config` (a TeamConfig) overrides the team."""
    from swarmsplat.graph.formulations import build_problem, initial_scales
    from swarmsplat.graph.metrics import ate
    from swarmsplat.graph.solvers import solve
    from swarmsplat.graph.synthetic import make_team

    team = make_team(config or team_config(backbone, quick, seed))
    g = team.graph
    inliers = [n for n in team.gt_scales if n not in team.outliers]
    out = {"backbone": backbone, "poses": len(g.poses), "loops": len(g.loops()), "outliers": len(team.outliers),
           "components": len(g.components()),
           "length_km": _length_km(team.gt), "odometry_only_ate": ate(g.poses, team.gt), "cells": {}}
    if out["components"] > 1:
        log(f"[{backbone}] WARNING: {out['components']} connected components; ATE includes unaligned robots")
    log(f"[{backbone}] {out['poses']} poses, {out['loops']} loops ({out['outliers']} outliers), "
        f"{out['length_km']:.2f} km; odometry-only ATE {out['odometry_only_ate'][0]:.1f} m")
    for init_name, init in INITS:
        s0 = initial_scales(g, init, team.gt_scales)
        P = scaled_initial_poses(g, s0)
        out["cells"][f"init/{init}"] = {"ate": ate(P, team.gt)}
        for row, form, solver in ROWS:
            if solver == "gnc" and not gnc:
                continue
            problem = build_problem(g, form, init, initial_poses=P, gt_scales=team.gt_scales)
            res = solve(problem, solver)
            cell = {"ate": ate(res.poses, team.gt), "time_s": res.time_s, "iterations": res.iterations,
                    "final_error": res.final_error}
            if solver == "gnc":
                rej = set(res.rejected)
                cell.update(rejected=len(rej), outliers_rejected=len(rej & team.outliers))
            if res.scales:
                q = np.array([res.scales[n] / team.gt_scales[n] for n in inliers if n in res.scales])
                cell["scale_ratio_median"] = float(np.median(q))
                cell["scale_ratio_p10_p90"] = [float(np.percentile(q, 10)), float(np.percentile(q, 90))]
            out["cells"][f"{row}/{init}"] = cell
            log(f"[{backbone}] {row:7s} {init_name:15s} ATE {cell['ate'][0]:7.2f} ± {cell['ate'][1]:6.2f} m "
                f"time {res.time_s:7.2f} s" + (f"  rejected {cell['rejected']} ({cell['outliers_rejected']} of "
                                                f"{len(team.outliers)} outliers)" if solver == "gnc" else ""))
    return out


def _length_km(gt) -> float:
    keys = sorted(gt)
    P = np.stack([gt[k][:3, 3] for k in keys])
    same = np.array([(a >> 56) == (b >> 56) for a, b in zip(keys[:-1], keys[1:])])
    return float(np.linalg.norm(np.diff(P, axis=0), axis=1)[same].sum() / 1000.0)


def markdown(result: dict) -> str:
    head = "| | " + " | ".join(f"{n} ATE (m) | {n} time (s)" for n, _ in INITS) + " |"
    lines = [head, "|" + "---|" * (1 + 2 * len(INITS))]
    for row, _, _ in ROWS:
        cells = []
        for _, init in INITS:
            c = result["cells"].get(f"{row}/{init}")
            cells += ([f"{c['ate'][0]:.2f} ± {c['ate'][1]:.2f}", f"{c['time_s']:.2f}"] if c else ["—", "—"])
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    init_ate = " / ".join(f"{result['cells'][f'init/{i}']['ate'][0]:.2f}" for _, i in INITS)
    return "\n".join(lines) + (f"\n\n{result['poses']} poses, {result['loops']} loops ({result['outliers']} "
                               f"outliers), {result['length_km']:.2f} km, {result.get('components', 1)} connected "
                               f"component(s). Odometry alone (each robot in its own start frame): ATE "
                               f"{result['odometry_only_ate'][0]:.1f} m. Chordal initial estimate (GT / raw / "
                               f"odometry scale): {init_ate} m.")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.flocc_experiment", description=__doc__.splitlines()[0])
    p.add_argument("--json", dest="json_out", required=True)
    p.add_argument("--md", dest="md_out")
    p.add_argument("--quick", action="store_true",
                   help="250 m per robot on a 100 m grid and 600 loops instead of 583 m on 200 m and 2000")
    p.add_argument("--odometry", nargs="+", choices=sorted(BACKBONES), default=["vio", "lio"])
    p.add_argument("--no-gnc", action="store_true", help="skip the GNC rows (the slow ones)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    from .common import machine_info, write_results

    t0 = time.perf_counter()
    report = {"machine": machine_info(), "quick": args.quick, "seed": args.seed, "backbones": {}}
    md = []
    for b in args.odometry:
        res = run_backbone(b, args.quick, gnc=not args.no_gnc, seed=args.seed,
                           log=lambda m: print(m, file=sys.stderr))
        report["backbones"][b] = res
        md.append(f"#### {b.upper()} odometry\n\n{markdown(res)}\n")
    report["total_s"] = time.perf_counter() - t0
    text = "\n".join(md)
    print(text)
    write_results(args.json_out, args.md_out, report, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
