"""The ROS side of a run: `swarmsplat bag-info BAG [--json OUT]` lists a bag's topics, types, message counts and
rates, and the topics a run would take from it (ROS 1 .bag, ROS 2 bag folder, bare .mcap / .db3; no ROS install);
`swarmsplat export RUN --to mcap|rosbag2|rosbag1 [--out PATH]` writes a run's trajectories, keyframe poses and loop
edges as standard ROS messages in a bag, to replay in rviz, Foxglove, rqt_bag or `ros2 bag play`."""

from __future__ import annotations

BAG_INFO_HELP = "List a bag's topics with their types, message counts and rates, and the topics a run would take."
EXPORT_HELP = ("Write a run's trajectories (geometry_msgs/PoseStamped, /tf), keyframe poses (nav_msgs/Path) and loop "
               "edges (visualization_msgs/MarkerArray) as a ROS 2 bag (MCAP or SQLite) or a ROS 1 bag.")


def register(sub) -> None:
    register_bag_info(sub)
    register_export(sub)


def register_bag_info(sub) -> None:
    p = sub.add_parser("bag-info", help="list a bag's topics (types, counts, rates) and what a run takes from it",
                       description=BAG_INFO_HELP)
    p.add_argument("bag", help="a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml) or a .mcap / .db3 file")
    p.add_argument("--json", metavar="OUT", help="also write the listing as JSON")
    p.set_defaults(func=run_bag_info)


def run_bag_info(args) -> int:
    from pathlib import Path

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_file
    from swarmsplat.slam.io.bags import bag_info, format_info, is_bag
    from swarmsplat.slam.io.jsonio import write_json

    if not Path(args.bag).exists():
        raise InputError(f"bag not found: {args.bag}")
    if not is_bag(args.bag):
        raise InputError(f"{args.bag}: not a bag (expected .bag, .mcap, .db3 or a ROS 2 bag folder with "
                         "metadata.yaml)")
    if args.json:
        output_file(args.json, "--json", create=False)
    info = bag_info(args.bag)
    print(format_info(info))
    if args.json:
        write_json(args.json, info)
    return 0


def register_export(sub) -> None:
    p = sub.add_parser("export", help="a run's trajectories, keyframes and loop edges as a ROS bag",
                       description=EXPORT_HELP)
    p.add_argument("run", help="a run's output folder (swarmsplat run / demo / agent)")
    p.add_argument("--to", default="mcap", metavar="FORMAT",
                   help="mcap (ROS 2 bag, MCAP storage; default), rosbag2 (ROS 2 bag, SQLite storage) or rosbag1")
    p.add_argument("--out", help="the bag to write (a new path; default: RUN/bag_<FORMAT>, .bag for rosbag1)")
    p.add_argument("--frame-id", default="map", help="the fixed frame of the poses (default: map)")
    p.set_defaults(func=run_export)


def run_export(args) -> int:
    from pathlib import Path

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.bags.export import TARGETS, export_run

    if args.to not in TARGETS:
        raise InputError(f"--to {args.to!r}: expected one of {', '.join(TARGETS)}")
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    out = Path(args.out) if args.out else run_dir / (f"bag_{args.to}" + (".bag" if args.to == "rosbag1" else ""))
    counts = export_run(run_dir, out, args.to, frame_id=args.frame_id)
    width = max(map(len, counts), default=5)
    for topic, n in sorted(counts.items()):
        print(f"{topic:<{width}}  {n:>6}")
    print(f"wrote {out}")
    return 0
