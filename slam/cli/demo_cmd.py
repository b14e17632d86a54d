"""`swarmsplat demo [--out DIR] [--preset default|tiny] [--kernels ...] [--device ...]`: generate the synthetic
3-agent dataset, run the GRAND-SLAM team on it, evaluate, and write a report (DIR/results/report.md)."""

from __future__ import annotations

from swarmsplat.slam.cli import add_backend_flags
from swarmsplat.slam.cli.view_cmd import add_live_view_flags, live_view, serve_result


def register(sub) -> None:
    p = sub.add_parser("demo", help="generate a 3-agent dataset, run the team, evaluate and write a report",
                       description="Generate the synthetic 3-agent RGB-D dataset (cached in DIR/dataset), run the "
                                   "GRAND-SLAM team on it, evaluate, and write DIR/results/report.md with the "
                                   "trajectories, merged map, loop closures and metrics.")
    p.add_argument("--out", default="swarmsplat_demo", help="output folder (default: ./swarmsplat_demo); the "
                                                            "dataset is cached in DIR/dataset")
    p.add_argument("--preset", choices=["default", "tiny"], default="default",
                   help="default: 3 agents x 120 frames; tiny: 2 agents x 10 frames (a quick check)")
    p.add_argument("--seed", type=int, help="generator seed (default: the preset's)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_live_view_flags(p)
    add_backend_flags(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import json

    from swarmsplat.slam.run.demo import run_demo

    live = live_view(args)  # a taken port fails before the run starts
    m = run_demo(args.out, preset=args.preset, kernels=args.kernels, device=args.device, seed=args.seed,
                 progress=not args.quiet, observer=live)
    keys = ["ate_rmse_team", "ate_rmse_team_agents", "joined_agents", "unjoined_agents", "psnr", "ssim", "depth_l1",
            "loops_accepted", "loop_candidates"]
    summary = {k: m.get(k) for k in keys}
    summary["agents"] = {a["name"]: {"ate_rmse": a.get("ate_rmse"), "ate_rmse_no_lc": a.get("ate_rmse_no_lc")}
                         for a in m["agents"]}
    summary["time_s"] = m["demo"]["total_s"]
    print(json.dumps(summary, indent=1))
    return serve_result(live, args.out)
