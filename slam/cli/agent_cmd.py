"""`swarmsplat agent SOURCE --out DIR`: one GRAND-SLAM agent on a robot. SOURCE `zenoh/[PREFIX]` reads live ROS 2
RGB-D topics over Zenoh (the Zenoh-ROS 2 bridge or rmw_zenoh) and publishes each tracked pose back as
geometry_msgs/PoseStamped; any other SOURCE is a recording (a sequence folder or a bag), run as `swarmsplat run`
runs it."""

from __future__ import annotations

from swarmsplat.slam.cli import add_backend_flags
from swarmsplat.slam.cli.config_flags import add_config_flags

LIVE = "zenoh/"


def register(sub) -> None:
    p = sub.add_parser("agent", help="one agent on a robot: live ROS 2 topics over Zenoh (or a recording)",
                       description=__doc__.splitlines()[0] + " " + " ".join(__doc__.splitlines()[1:]))
    p.add_argument("source", nargs="?", help="zenoh/[KEY_PREFIX] for live topics, or a sequence folder / bag")
    p.add_argument("--source", dest="source_opt", metavar="SOURCE", help="the same as the positional SOURCE")
    p.add_argument("--out", required=True, help="output folder")
    add_config_flags(p)
    p.add_argument("--topics", metavar="ROLE=TOPIC,...",
                   help="ROS 2 topics: color, depth, info (live; default /camera/color/image_raw, "
                        "/camera/depth/image_raw, /camera/color/camera_info) or any of color, depth, info, "
                        "odometry, gt for a bag (default: found)")
    p.add_argument("--publish", metavar="KEY", help="Zenoh key of the published poses (default: "
                                                   "swarmsplat/<name>/pose; the keyframe path goes to KEY/path)")
    p.add_argument("--name", default="live", help="the agent's name (default: live)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p.add_argument("--frames", type=int, default=0, help="stop after N frames (default: until Ctrl-C)")
    p.add_argument("--idle-timeout", type=float, default=0.0, metavar="S",
                   help="stop after S seconds without a sample (default: never)")
    p.add_argument("--silent-warning", type=float, default=5.0, metavar="S",
                   help="warn when the topics have been silent for S seconds (default: 5)")
    p.add_argument("--camera-timeout", type=float, default=30.0, metavar="S",
                   help="give up when no camera_info arrives within S seconds (default: 30)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_backend_flags(p)
    p.set_defaults(func=run, kernels=None, device=None)


def run(args) -> int:
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_dir
    from swarmsplat.slam.cli.config_flags import load_config
    from swarmsplat.slam.io.bags import parse_topics

    source = args.source_opt or args.source
    if not source:
        raise InputError("give a SOURCE: zenoh/[KEY_PREFIX] for live ROS 2 topics, or a sequence folder or bag")
    if args.source and args.source_opt and args.source != args.source_opt:
        raise InputError(f"two sources given: {args.source} and --source {args.source_opt}")
    for flag, value in (("--frames", args.frames), ("--idle-timeout", args.idle_timeout),
                        ("--camera-timeout", args.camera_timeout), ("--silent-warning", args.silent_warning)):
        if value < 0:
            raise InputError(f"{flag} must be >= 0, got {value}")
    topics = parse_topics(args.topics)
    output_dir(args.out, "--out", create=False)
    cfg = load_config(args.config, {"--kernels": ("kernels.backend", args.kernels),
                                    "--device": ("kernels.device", args.device)}, preset=args.preset)
    if not source.startswith(LIVE):
        from swarmsplat.slam.io.datasets import load_sequence
        from swarmsplat.slam.run.sequence import run_sequence

        seq = load_sequence(source, topics=topics) if topics else load_sequence(source)
        m = run_sequence(seq, args.out, cfg, frames=args.frames or None, progress=not args.quiet)
        print(f"wrote {args.out} ({m['frames_tracked']} frames tracked)")
        return 0
    from swarmsplat.slam.io.live import PosePublisher, ZenohRos2Source
    from swarmsplat.slam.run.live import run_live

    unknown = set(topics) - {"color", "depth", "info"}
    if unknown:
        raise InputError(f"--topics: {', '.join(sorted(unknown))} cannot be read live; expected color, depth, info")
    src = ZenohRos2Source(source[len(LIVE):], topics, name=args.name, connect=args.connect, listen=args.listen)
    try:
        pub = PosePublisher(src.session, args.publish or f"swarmsplat/{args.name}/pose")
        m = run_live(src, args.out, cfg, publisher=pub, max_frames=args.frames, idle_timeout=args.idle_timeout,
                     camera_timeout=args.camera_timeout, silent_warning=args.silent_warning,
                     progress=not args.quiet)
    finally:
        src.close()
    lat = m["pose_latency_ms"]
    p50 = f", pose latency p50 {lat['p50']:.1f} ms / p95 {lat['p95']:.1f} ms" if lat["count"] else ""
    print(f"{m['frames_tracked']} frames tracked ({m['reason']}){p50}; wrote {args.out}")
    return 0
