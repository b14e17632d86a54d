"""`swarmsplat agent SOURCE --out DIR`: one GRAND-SLAM agent on a robot. SOURCE `zenoh/[PREFIX]` reads live ROS 2
RGB-D topics over Zenoh (the Zenoh-ROS 2 bridge or rmw_zenoh) and publishes its poses, TF, keyframe path, map and
loops as ROS 2 topics the way rmw_zenoh does (ROS 2 sees them); any other SOURCE is a recording (a sequence folder or a bag), run as `swarmsplat run`
runs it. With --server ENDPOINT the agent is a member of a team served by `swarmsplat server` (also registered
here): it sends its keyframes and submaps over Zenoh and the server closes the loops; on live topics it also
publishes what a lone agent does, corrected by the server."""

from __future__ import annotations

import contextlib

from swarmsplat.slam.cli import add_backend_flags
from swarmsplat.slam.cli.config_flags import add_config_flags

LIVE = "zenoh/"


def register(sub) -> None:
    p = sub.add_parser("agent", help="one agent on a robot: live ROS 2 topics over Zenoh (or a recording)",
                       description=__doc__.splitlines()[0] + " " + " ".join(__doc__.splitlines()[1:]))
    p.add_argument("source", nargs="?", help="zenoh/[KEY_PREFIX] for live topics, or a sequence folder / bag")
    p.add_argument("--source", dest="source_opt", metavar="SOURCE", help="the same as the positional SOURCE")
    p.add_argument("--out", help="output folder (required, except for a team member: --server)")
    add_config_flags(p)
    p.add_argument("--topics", metavar="ROLE=TOPIC,...",
                   help="ROS 2 topics: color, depth, info (live; default /camera/color/image_raw, "
                        "/camera/depth/image_raw, /camera/color/camera_info) or any of color, depth, info, "
                        "odometry, gt for a bag (default: found)")
    p.add_argument("--publish", metavar="TOPIC", help="the pose topic (default /swarmsplat/<name>/pose); with "
                   "--ros-keys bridge the plain Zenoh key of the poses, the keyframe path going to KEY/path")
    p.add_argument("--ros-keys", choices=("rmw", "bridge"), default="rmw",
                   help="how published topics are keyed: rmw (rmw_zenoh's keys, liveliness tokens and attachments: "
                        "ROS 2 sees them; default) or bridge (zenoh-bridge-ros2dds' plain keys)")
    p.add_argument("--domain-id", type=int, metavar="N",
                   help="ROS domain id of the published topics (default: ROS_DOMAIN_ID, else 0)")
    p.add_argument("--namespace", default="/", metavar="NS", help="the ROS node's namespace (default: /)")
    p.add_argument("--map-period", type=float, default=10.0, metavar="S",
                   help="publish the whole map every S seconds (0: at the end only; default: 10)")
    p.add_argument("--resume", action="store_true",
                   help="continue the agent killed in --out from its last checkpoint (live: on the frames that "
                        "arrive now; a recording: from the frame after the checkpoint; a team member: from the "
                        "round after it (live: the frames it logged since, then the ones that arrive now), "
                        "joining its server again)")
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
    p.add_argument("--server", action="append", default=[], metavar="ENDPOINT",
                   help="be a team member: send keyframes and submaps to `swarmsplat server` at this Zenoh "
                        "endpoint, e.g. tcp/192.168.1.10:7447 (recordings only)")
    p.add_argument("--id", type=int, metavar="K",
                   help="--server: this agent's index in the team, 0 .. N-1 (default: its position in a "
                        "multi-agent SOURCE, else the index the server gives --name)")
    p.add_argument("--split", metavar="RANGES",
                   help="--server: SOURCE is one sequence cut into agents as `swarmsplat run --split` cuts it; "
                        "this agent is the range named by --name or --id")
    p.add_argument("--run", default="team", help="--server: the team's Zenoh key prefix (default: team)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_backend_flags(p)
    p.set_defaults(func=run, kernels=None, device=None)
    register_server(sub)


def register_server(sub) -> None:
    p = sub.add_parser("server", help="the GRAND-SLAM team server for agents in other processes or machines",
                       description="Serve N team agents (`swarmsplat agent SOURCE --server ENDPOINT`) over Zenoh: "
                                   "close intra- and inter-agent loops, optimise the team's pose graph, send each "
                                   "agent its corrections and write the team's outputs to --out. A server started "
                                   "again on the same --out continues from its journal (link/journal.bin).")
    p.add_argument("--agents", type=int, required=True, metavar="N", help="agents in the team")
    p.add_argument("--out", required=True, help="output folder")
    add_config_flags(p)
    p.add_argument("--dataset", metavar="PATH",
                   help="the agents' multi-agent dataset, for the evaluation (ATE, renders); without it the "
                        "estimates, map, loops and link figures are written")
    p.add_argument("--split", metavar="RANGES", help="--dataset is one sequence cut into agents (as run --split)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (default: tcp/0.0.0.0:<link.port_base>)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to (a router or the agents), repeatable")
    p.add_argument("--run", default="team", help="the team's Zenoh key prefix (default: team)")
    p.add_argument("--ros-keys", choices=("rmw", "bridge", "off"), default="rmw",
                   help="the team's corrected trajectories, loops and merged map as ROS 2 topics /swarmsplat/team/..."
                        ": rmw (rmw_zenoh's keys; default), bridge (plain keys) or off")
    p.add_argument("--domain-id", type=int, metavar="N",
                   help="ROS domain id of the published topics (default: ROS_DOMAIN_ID, else 0)")
    p.add_argument("--map-period", type=float, default=10.0, metavar="S",
                   help="publish the merged map every S seconds (0: at the end only; default: 10)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_backend_flags(p)
    p.set_defaults(func=run_server, kernels=None, device=None)


def run_server(args) -> int:
    from swarmsplat.slam.cli.config_flags import load_config
    from swarmsplat.slam.run.team_link.processes import serve_command

    cfg = load_config(args.config, {"--kernels": ("kernels.backend", args.kernels),
                                    "--device": ("kernels.device", args.device)}, preset=args.preset, sets=args.config_set)
    from swarmsplat.kernels.errors import InputError

    dataset = args.dataset
    if args.split:
        if not dataset:
            raise InputError("--split cuts --dataset into agents: give --dataset too")
        from swarmsplat.slam.io.datasets import load_dataset
        from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence

        dataset = split_sequence(load_dataset(dataset).agents[0], parse_ranges(args.split))
    m = serve_command(args.agents, args.out, cfg, dataset=dataset, listen=args.listen, connect=args.connect,
                      run=args.run, progress=not args.quiet, ros_keys=args.ros_keys, domain=args.domain_id,
                      map_period=args.map_period)
    lost = m["link"]["lost_agents"]
    print(f"wrote {args.out}: {m['loops_accepted']} loops accepted, {m['link']['bytes_total'] / 1e6:.1f} MB on the "
          f"link" + (f"; lost: {', '.join(lost)}" if lost else ""))
    return 0


def _team_member(args, source: str, cfg) -> int:
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.run.team_link.processes import run_team_agent

    if source.startswith(LIVE):
        return _live_team_member(args, source, cfg)
    ds = load_dataset(source)
    if args.split:
        from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence

        if len(ds.agents) != 1:
            raise InputError(f"--split cuts one sequence into agents, but {source} holds {len(ds.agents)}")
        ds = split_sequence(ds.agents[0], parse_ranges(args.split))
    names = [s.name for s in ds.agents]
    k = args.id
    if k is None and len(names) > 1:
        if args.name not in names:
            raise InputError(f"--name {args.name}: {source} holds agents {', '.join(names)}; name one or give --id")
        k = names.index(args.name)
    if k is not None and len(names) > 1 and k >= len(names):
        raise InputError(f"--id {k}: {source} holds agents 0 .. {len(names) - 1}")
    seq = ds.agents[0] if len(names) == 1 else ds.agents[k]
    name = args.name if args.name != "live" else seq.name
    if k is None:  # one sequence and no --id: the server gives this agent its index by name
        k = _ask_index(args, name, cfg)
    m = run_team_agent(seq, k, cfg, name=name, connect=args.server + args.connect, listen=args.listen, run=args.run,
                       frames=args.frames or None, progress=not args.quiet, out=args.out, resume=args.resume)
    print(f"{name}: {m['bytes']['sent_total'] / 1e6:.2f} MB sent, {m['resent']} resent, {m['dropped_images']} "
          f"keyframe images dropped" + ("" if m["acknowledged"] else "; NOT all acknowledged by the server"))
    return 0 if m["acknowledged"] else 1


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
    cfg = load_config(args.config, {"--kernels": ("kernels.backend", args.kernels),
                                    "--device": ("kernels.device", args.device)}, preset=args.preset, sets=args.config_set)
    if args.server:
        if args.resume and not args.out:
            raise InputError("--resume continues the team agent whose checkpoint is in --out: give --out")
        return _team_member(args, source, cfg)
    for flag in ("id", "split"):
        if getattr(args, flag) is not None:
            raise InputError(f"--{flag} chooses a team member's sequence: give --server ENDPOINT too")
    if not args.out:
        raise InputError("--out: give an output folder (only a team member, --server, may run without one)")
    output_dir(args.out, "--out", create=False)
    if not source.startswith(LIVE):
        from swarmsplat.slam.io.datasets import load_sequence
        from swarmsplat.slam.run.sequence import run_sequence

        seq = load_sequence(source, topics=topics) if topics else load_sequence(source)
        m = run_sequence(seq, args.out, cfg, frames=args.frames or None, progress=not args.quiet,
                         resume=args.resume)
        print(f"wrote {args.out} ({m['frames_tracked']} frames tracked)")
        return 0
    from swarmsplat.slam.run.live import run_live

    with _live_topics(args, source, topics) as (src, pub):
        m = run_live(src, args.out, cfg, publisher=pub, max_frames=args.frames, idle_timeout=args.idle_timeout,
                     camera_timeout=args.camera_timeout, silent_warning=args.silent_warning,
                     map_period=args.map_period, progress=not args.quiet, resume=args.resume)
    lat = m["pose_latency_ms"]
    p50 = f", pose latency p50 {lat['p50']:.1f} ms / p95 {lat['p95']:.1f} ms" if lat["count"] else ""
    print(f"{m['frames_tracked']} frames tracked ({m['reason']}){p50}; wrote {args.out}")
    return 0


def _live_team_member(args, source: str, cfg) -> int:
    """`swarmsplat agent zenoh/[PREFIX] --server ENDPOINT --id K`: a team member on live ROS 2 topics."""
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.bags import parse_topics
    from swarmsplat.slam.run.team_link.live_agent import run_live_team_agent

    if args.split:
        raise InputError("--split cuts a recording into agents; live topics are one agent")
    with _live_topics(args, source, parse_topics(args.topics)) as (src, pub):
        k = args.id if args.id is not None else _ask_index(args, args.name, cfg)
        m = run_live_team_agent(src, k, cfg, name=args.name, connect=args.server, run=args.run,
                                publisher=pub, max_frames=args.frames, idle_timeout=args.idle_timeout,
                                camera_timeout=args.camera_timeout, silent_warning=args.silent_warning,
                                map_period=args.map_period, progress=not args.quiet, out=args.out,
                                resume=args.resume)
    again = f", {m['frames_replayed']} logged frames tracked again" if m["frames_replayed"] else ""
    print(f"{args.name}: {m['frames_tracked']} frames tracked ({m['reason']}{again}), {m['poses_published']} poses "
          f"published, {m['bytes']['sent_total'] / 1e6:.2f} MB sent"
          + ("" if m["acknowledged"] else "; NOT all acknowledged by the server"))
    return 0 if m["acknowledged"] else 1


@contextlib.contextmanager
def _live_topics(args, source: str, topics: dict):
    """(the live source on `source`'s topics, the publisher of its poses), closed on the way out."""
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.live import PosePublisher, ZenohRos2Source
    from swarmsplat.slam.io.ros2 import AgentTopics, Ros2Node, domain_id
    from swarmsplat.slam.io.ros2.publishers import ros_token

    unknown = set(topics) - {"color", "depth", "info"}
    if unknown:
        raise InputError(f"--topics: {', '.join(sorted(unknown))} cannot be read live; expected color, depth, info")
    if args.map_period < 0:
        raise InputError(f"--map-period must be >= 0, got {args.map_period}")
    domain = domain_id(args.domain_id)
    src = ZenohRos2Source(source[len(LIVE):], topics, name=args.name, connect=args.connect, listen=args.listen,
                          domain=domain)
    node = pub = None
    try:
        if args.ros_keys == "bridge" and args.publish:
            pub = PosePublisher(src.session, args.publish)
        else:
            node = Ros2Node(src.session, "swarmsplat_" + ros_token(args.name), namespace=args.namespace,
                            domain=domain, form=args.ros_keys)
            for role, topic in src.topics.items():  # announced, so a ROS 2 graph shows what the agent reads
                node.subscription_token(topic, "sensor_msgs/msg/CameraInfo" if role == "info"
                                        else "sensor_msgs/msg/Image")
            pub = AgentTopics(node, args.name, topics={"pose": args.publish} if args.publish else None)
        yield src, pub
    finally:
        if pub is not None:
            pub.close()
        if node is not None:
            node.close()
        src.close()


def _ask_index(args, name: str, cfg) -> int:
    """This agent's index, asked of the team server by name (slam.run.team_link.registry)."""
    import sys

    from swarmsplat.slam.run.team_link.processes import check_member
    from swarmsplat.slam.run.team_link.registry import ask_index

    check_member(0, args.server + args.connect, args.listen)
    k = ask_index(name, connect=args.server + args.connect, listen=args.listen, run=args.run,
                  timeout=cfg.link.connect_timeout_s,
                  say=None if args.quiet else (lambda text: print(text, file=sys.stderr)))
    if not args.quiet:
        print(f"{name}: the team server gave this agent index {k}", file=sys.stderr)
    return k
