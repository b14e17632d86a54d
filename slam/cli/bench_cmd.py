"""`swarmsplat bench SUBJECT ...`: the perf/ driver, from the console script."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bench", help="run perf/ benchmarks (same flags as `python -m perf`)", add_help=False)
    p.add_argument("rest", nargs="...", help="arguments for `python -m perf`")
    p.set_defaults(func=run)


def run(args) -> int:
    from perf.__main__ import main as perf_main

    return perf_main(args.rest)
