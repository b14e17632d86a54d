"""`swarmsplat run DATASET --out DIR [--config YAML] [--preset NAME] [--kernels ...] [--device ...] [--frames N]
[--split R]`: one agent's GRAND-SLAM over one RGB-D sequence (trajectory.txt (TUM), map.ply, metrics.json,
loops.csv, plots, config.yaml in DIR), or a team on a multi-agent dataset or on a single sequence split into agents
(--split; the config's `server` and `team` sections apply)."""

from __future__ import annotations

from contextlib import contextmanager

from swarmsplat.slam.cli import add_backend_flags
from swarmsplat.slam.cli.config_flags import add_config_flags
from swarmsplat.slam.cli.view_cmd import add_live_view_flags, live_view, serve_result


def register(sub) -> None:
    p = sub.add_parser("run", help="run RGB-D Gaussian-splatting SLAM on a sequence (one agent) or a team",
                       description="One agent's GRAND-SLAM over one RGB-D sequence: writes trajectory.txt and "
                                   "trajectory_no_lc.txt (TUM), keyframes.txt, map.ply (3DGS), metrics.json, "
                                   "loops.csv, trajectory.png and config.yaml to --out; while it runs, "
                                   "progress/poses.tum (every frame up to the last keyframe, appended and "
                                   "fsync'd at each keyframe; per agent progress/<agent>.tum in a team) and "
                                   "progress/checkpoint.pkl (what --resume continues from; removed when the run "
                                   "completes). "
                                   "A multi-agent dataset, or a sequence cut into agents with --split, runs as a "
                                   "team (inter-agent loops, one global pose graph, merged map). "
                                   "--kernels/--device override the config file's kernels section; a team run "
                                   "also reads its server and team sections.")
    p.add_argument("dataset", help="sequence folder (our format, TUM RGB-D, Redwood / ICL-NUIM, Replica, ScanNet "
                                   "export, 7-Scenes seq-NN), a bag (ROS 1 .bag, ROS 2 bag folder, .mcap, .db3) "
                                   "or a multi-agent dataset (dataset.yaml, Multiagent Replica, a 7-Scenes scene "
                                   "with several sequences, a bag with /robotN/ namespaces, a folder of bags), "
                                   "which runs as a team")
    p.add_argument("--out", required=True, help="output folder")
    add_config_flags(p)
    p.add_argument("--frames", type=int, help="process at most N frames (per agent)")
    p.add_argument("--topics", metavar="ROLE=TOPIC,...",
                   help="a bag's topics, any of color, depth, info, odometry, gt (e.g. color=/cam/color/image_raw,"
                        "depth=/cam/aligned_depth_to_color/image_raw); the rest are found (swarmsplat bag-info "
                        "shows the choice)")
    p.add_argument("--split", metavar="RANGES",
                   help="run one sequence as a team: comma-separated half-open frame ranges START:STOP, one agent "
                        "each, e.g. 0:3,3:5 (agent_0 frames 0-2, agent_1 frames 3-4; ranges may overlap, an empty "
                        "START/STOP means the start/end). Each agent starts in its own frame and joins the "
                        "global frame at its first accepted inter-agent loop")
    p.add_argument("--processes", action="store_true",
                   help="a team with its agents in separate processes: the server runs here and one `swarmsplat "
                        "agent --server` process per agent, over Zenoh on localhost; the same outputs, plus the "
                        "link's bytes (metrics.json link, report.md)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out that was killed or interrupted, from its last checkpoint "
                        "(progress/checkpoint.pkl; one agent or a team in one process; with --processes the "
                        "server's journal and each agent's checkpoint in link/<agent>/; the dataset, --split and "
                        "config must be the run's own)")
    p.add_argument("--realtime", action="store_true",
                   help="real-time mode (one agent): frames arrive at the sensor's rate, each pose is emitted as its "
                        "frame is tracked, mapping runs beside tracking, frames the tracker cannot take in time are "
                        "dropped and counted (metrics.json realtime, report.md; config runtime.*)")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="--realtime: replay at HZ frames per second instead of the dataset's timestamps")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable frame (default: skip it with a warning; metrics.json lists "
                        "it under skipped_frames)")
    add_live_view_flags(p)
    add_backend_flags(p)
    p.set_defaults(func=run, kernels=None, device=None)  # not given: the config's kernels section


def run(args) -> int:
    import json

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_dir
    from swarmsplat.slam.cli.config_flags import load_config
    from swarmsplat.slam.run.sequence import run_sequence

    ranges = None
    if args.split is not None:
        from swarmsplat.slam.io.datasets.split import parse_ranges

        ranges = parse_ranges(args.split)  # bad syntax fails before any loading
    if args.frames is not None and args.frames < 1:
        raise InputError(f"--frames must be at least 1, got {args.frames}")
    if args.rate is not None and not 0 < args.rate < float("inf"):
        raise InputError(f"--rate must be a frame rate above 0 (Hz), got {args.rate:g}")
    output_dir(args.out, "--out", create=False)  # a file or an unwritable place fails before any loading
    cfg = load_config(args.config, {"--kernels": ("kernels.backend", args.kernels),
                                    "--device": ("kernels.device", args.device),
                                    "--realtime": ("runtime.realtime", args.realtime or None),
                                    "--rate": ("runtime.rate", args.rate)}, preset=args.preset, sets=args.config_set)
    if args.rate is not None and not cfg.runtime.realtime:
        raise InputError("--rate sets the replay rate of real-time mode: give --realtime too")
    from swarmsplat.slam.io.datasets import load_dataset

    if args.topics:
        from swarmsplat.slam.io.bags import is_bag, parse_topics

        from pathlib import Path

        topics = parse_topics(args.topics)
        root = Path(args.dataset)
        if not (is_bag(root) or (root.is_dir() and any(is_bag(q) for q in root.iterdir()))):
            raise InputError(f"--topics chooses a bag's topics, but {args.dataset} is not a bag")
        ds = load_dataset(args.dataset, topics=topics)
    else:
        ds = load_dataset(args.dataset)
    if ds.meta.get("layout") == "bag":  # the topics taken, found or given: say which
        import sys

        for seq, chosen in zip(ds.agents, ds.meta["topics"]):
            if not args.quiet:
                print(f"[{seq.name}] topics: " + ", ".join(f"{k} {v}" for k, v in chosen.items()), file=sys.stderr)
            if not seq.is_rgbd:
                raise InputError(f"{args.dataset}: no depth topic next to {chosen['color']} (a sensor_msgs/Image "
                                 "with 'depth' in its name); GRAND-SLAM needs RGB-D: give one with --topics "
                                 "depth=TOPIC (swarmsplat bag-info lists the topics)")
    live = live_view(args)  # a taken port fails before the run starts
    if ranges is not None:
        if len(ds) != 1:
            raise InputError(f"--split cuts one sequence into agents, but {args.dataset} already holds {len(ds)} "
                             f"agents' sequences")
        from swarmsplat.slam.io.datasets.split import split_sequence

        try:
            ds = split_sequence(ds.agents[0], ranges)
        except InputError as e:
            raise InputError(f"--split: {e}") from None
    if args.processes and len(ds) < 2:
        raise InputError(f"--processes runs a team's agents in separate processes, but {args.dataset} holds one "
                         f"sequence: give a multi-agent dataset or cut it with --split")
    if len(ds) > 1:
        if cfg.runtime.realtime:
            raise InputError(f"--realtime runs one agent, but {args.dataset} holds {len(ds)} agents' sequences")
        # A multi-agent dataset runs as a team: inter-agent loops, one global pose graph, merged map.
        from swarmsplat.slam.run.team import run_team

        if args.processes:
            from swarmsplat.slam.run.team_link.processes import run_team_processes

            m = run_team_processes(args.dataset, args.out, cfg, frames=args.frames, split=args.split, loaded=ds,
                                   progress=not args.quiet, resume=args.resume)
        else:
            with _resumable(args.out):
                m = run_team(ds, args.out, cfg, frames=args.frames, progress=not args.quiet, observer=live,
                             strict=args.strict, resume=args.resume)
        keys = ("name", "frames", "in_global_frame", "ate_rmse", "ate_rmse_no_lc", "psnr")
        summary = {
            "agents": [{k: a.get(k) for k in keys} for a in m["agents"]],
            "ate_rmse_team": m.get("ate_rmse_team"), "ate_rmse_team_agents": m.get("ate_rmse_team_agents"),
            "joined_agents": m.get("joined_agents"), "unjoined_agents": m.get("unjoined_agents"),
            "psnr": m.get("psnr"), "loops_accepted": m.get("loops_accepted"),
            "loops": {kind: m.get("loops", {}).get(kind) for kind in ("intra", "inter")},
        }
        print(json.dumps(summary, indent=1))
        return serve_result(live, args.out)
    keys = ["frames", "keyframes", "submaps", "gaussians", "loops_accepted", "ate_rmse", "psnr", "ssim", "depth_l1", "fps"]
    if cfg.runtime.realtime:  # frames at the sensor's rate, mapping beside tracking (slam.run.realtime)
        from swarmsplat.slam.run.realtime.run import run_realtime, summary

        if args.resume or live is not None:
            raise InputError(f"--realtime does not take {'--resume' if args.resume else '--view'}")
        m = run_realtime(ds.agents[0], args.out, cfg, frames=args.frames, progress=not args.quiet, strict=args.strict)
        print(json.dumps({**{k: m.get(k) for k in keys}, "realtime": summary(m)}, indent=1))
        return 0
    with _resumable(args.out):
        m = run_sequence(ds.agents[0], args.out, cfg, frames=args.frames, progress=not args.quiet, observer=live,
                         strict=args.strict, resume=args.resume)
    print(json.dumps({k: m.get(k) for k in keys}, indent=1))
    return serve_result(live, args.out)


@contextmanager
def _resumable(out: str):
    """A run stopped by a full disk: its one line says what --resume needs (the folder keeps its last checkpoint
    and journal whole, slam.run.checkpoint)."""
    from swarmsplat.kernels.errors import OutputError

    try:
        yield
    except OutputError as e:
        if not e.full:
            raise
        raise OutputError(f"{e}; {out} keeps the run's last checkpoint: free some space, then run the same "
                          "command with --resume", full=True, errno=e.errno) from e
