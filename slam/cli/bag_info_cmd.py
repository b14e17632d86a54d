"""`swarmsplat bag-info BAG [--json OUT]`: a bag's topics, types, message counts and rates, and the topics a run
would take from it (ROS 1 .bag, ROS 2 bag folder, bare .mcap / .db3; no ROS install)."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bag-info", help="list a bag's topics (types, counts, rates) and what a run takes from it",
                       description=__doc__.splitlines()[0])
    p.add_argument("bag", help="a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml) or a .mcap / .db3 file")
    p.add_argument("--json", metavar="OUT", help="also write the listing as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
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
