"""`swarmsplat run DATASET --out DIR [--config YAML] [--kernels ...] [--device ...] [--frames N]`: one agent's
GRAND-SLAM over one RGB-D sequence; writes trajectory.txt (TUM), map.ply, metrics.json, loops.csv, plots and
config.yaml to DIR."""

from __future__ import annotations

from slam.cli import add_backend_flags


def register(sub) -> None:
    p = sub.add_parser("run", help="run RGB-D Gaussian-splatting SLAM on a sequence (one agent)",
                       description="One agent's GRAND-SLAM over one RGB-D sequence: writes trajectory.txt (TUM), "
                                   "map.ply (3DGS), metrics.json, loops.csv, trajectory.png and config.yaml to --out. "
                                   "--kernels/--device override the config file's kernels section.")
    p.add_argument("dataset", help="sequence folder (our format, TUM RGB-D, Redwood, Replica) or a multi-agent "
                                   "dataset (dataset.yaml, Multiagent Replica), which runs as a team")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="YAML file overriding the default settings")
    p.add_argument("--frames", type=int, help="process at most N frames")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    add_backend_flags(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import json

    from slam.config import SlamConfig
    from slam.run import run_sequence

    cfg = SlamConfig.from_yaml(args.config, overrides={"kernels": {"backend": args.kernels, "device": args.device}})
    if args.frames is not None and args.frames < 1:
        from kernels.errors import InputError

        raise InputError(f"--frames must be at least 1, got {args.frames}")
    from slam.datasets import load_dataset

    ds = load_dataset(args.dataset)
    if len(ds) > 1:
        # A multi-agent dataset runs as a team: inter-agent loops, one global pose graph, merged map (issue 7).
        from slam.team import run_team

        m = run_team(ds, args.out, cfg, frames=args.frames, progress=not args.quiet)
        summary = {
            "agents": [{k: a.get(k) for k in ("name", "ate_rmse", "ate_rmse_no_lc", "psnr")} for a in m["agents"]],
            "ate_rmse_team": m.get("ate_rmse_team"), "psnr": m.get("psnr"), "loops_accepted": m.get("loops_accepted"),
        }
        print(json.dumps(summary, indent=1))
        return 0
    m = run_sequence(args.dataset, args.out, cfg, frames=args.frames, progress=not args.quiet)
    keys = ["frames", "keyframes", "submaps", "gaussians", "loops_accepted", "ate_rmse", "psnr", "ssim", "depth_l1", "fps"]
    print(json.dumps({k: m.get(k) for k in keys}, indent=1))
    return 0
