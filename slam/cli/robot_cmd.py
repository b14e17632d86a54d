"""`swarmsplat robot --id K DATASET --out DIR ...`: one robot of a monocular dataset as its own process, talking
to the others over Zenoh (peer-to-peer on this machine or a network). Without --start-time it prints `ready`
once connected and reads the epoch time of tick 0 from stdin (what `swarmsplat swarm --processes` does, handing
every robot the same --config file)."""

from __future__ import annotations


def register(sub) -> None:
    from swarmsplat.slam.cli.swarm_cmd import add_swarm_options

    p = sub.add_parser("robot", help="run one robot over Zenoh (see `swarm --processes`)")
    p.add_argument("--id", type=int, required=True, help="robot id: the dataset's K-th agent")
    add_swarm_options(p)
    p.add_argument("--start-time", type=float, help="epoch seconds of tick 0 (default: read from stdin)")
    p.add_argument("--run", default="swarmsplat", help="run name (Zenoh key prefix) shared by the robots")
    p.set_defaults(func=run)


def run(args) -> int:
    from swarmsplat.slam.cli.swarm_cmd import swarm_config
    from swarmsplat.slam.run.swarm_processes import run_robot

    run_robot(args.dataset, args.id, args.out, swarm_config(args), start_time=args.start_time, run=args.run)
    return 0
