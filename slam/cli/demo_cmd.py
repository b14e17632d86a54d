"""`swarmsplat demo [--out DIR] [--preset default|tiny] [--config YAML] [--kernels ...] [--device ...]`: generate
the synthetic 3-agent dataset, run the GRAND-SLAM team on it, evaluate, and write a report
(DIR/results/report.md). The settings are the preset file configs/demo.yaml (or demo-tiny.yaml), then --config,
then the flags."""

from __future__ import annotations

from swarmsplat.slam.cli import add_backend_flags
from swarmsplat.slam.cli.config_flags import add_config_flags
from swarmsplat.slam.cli.view_cmd import add_live_view_flags, live_view, serve_result


def register(sub) -> None:
    p = sub.add_parser("demo", help="generate a 3-agent dataset, run the team, evaluate and write a report",
                       description="Generate the synthetic 3-agent RGB-D dataset (cached in DIR/dataset), run the "
                                   "GRAND-SLAM team on it, evaluate, and write DIR/results/report.md with the "
                                   "trajectories, merged map, loop closures and metrics.")
    p.add_argument("--out", default="swarmsplat_demo", help="output folder (default: ./swarmsplat_demo); the "
                                                            "dataset is cached in DIR/dataset")
    p.add_argument("--preset", choices=["default", "tiny"], default="default",
                   help="default: 3 agents x 120 frames (configs/demo.yaml); tiny: 2 agents x 10 frames, a quick "
                        "check (configs/demo-tiny.yaml)")
    add_config_flags(p, preset=False)
    p.add_argument("--seed", type=int, help="generator seed (default: the config's demo.seed, else the generator "
                                            "preset's)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_live_view_flags(p)
    add_backend_flags(p)
    p.set_defaults(func=run, kernels=None, device=None)  # not given: the config's kernels section


def run(args) -> int:
    import json

    from swarmsplat.slam.cli.config_flags import load_config
    from swarmsplat.slam.run.demo import PRESETS, run_demo

    cfg = load_config(args.config, {"--kernels": ("kernels.backend", args.kernels),
                                    "--device": ("kernels.device", args.device),
                                    "--seed": ("demo.seed", args.seed)}, preset=PRESETS[args.preset], sets=args.config_set)
    live = live_view(args)  # a taken port fails before the run starts
    m = run_demo(args.out, preset=args.preset, config=cfg, progress=not args.quiet, observer=live)
    keys = ["ate_rmse_team", "ate_rmse_team_agents", "joined_agents", "unjoined_agents", "psnr", "ssim", "depth_l1",
            "loops_accepted", "loop_candidates"]
    summary = {k: m.get(k) for k in keys}
    summary["agents"] = {a["name"]: {"ate_rmse": a.get("ate_rmse"), "ate_rmse_no_lc": a.get("ate_rmse_no_lc")}
                         for a in m["agents"]}
    summary["time_s"] = m["demo"]["total_s"]
    print(json.dumps(summary, indent=1))
    return serve_result(live, args.out)
