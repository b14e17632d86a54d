"""The `swarmsplat` console script: a thin layer of subcommands over keyword-argument library functions.

Each subcommand lives in its own module `slam/cli/<name>_cmd.py` exposing
    register(subparsers) -> None   # adds its parser and sets `func=run` as the default
    run(args) -> int               # translates the namespace into explicit keyword arguments
Heavy imports happen inside `run`. SwarmsplatError subclasses become one line on stderr and their exit code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Subcommand modules, in the order `swarmsplat --help` lists them. A module that is missing is skipped, so a
# partial checkout still runs what it has.
COMMANDS = [
    "demo_cmd",
    "generate_cmd",
    "run_cmd",
    "eval_cmd",
    "graph_cmd",
    "pairs_cmd",
    "swarm_cmd",
    "robot_cmd",
    "bench_cmd",
    "view_cmd",
]


def add_backend_flags(p: argparse.ArgumentParser) -> None:
    """--kernels / --device, shared by every subcommand that launches kernels."""
    p.add_argument("--kernels", choices=["warp", "taichi"], default="warp", help="kernel backend (default: warp)")
    p.add_argument("--device", choices=["cpu", "cuda", "vulkan"], default="cpu",
                   help="kernel device (default: cpu; vulkan: --kernels taichi only)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swarmsplat",
        description="Collaborative multi-robot SLAM: GRAND-SLAM (RGB-D Gaussian splatting) and FLOCC-SLAM loop closing.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks for errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from kernels.errors import SwarmsplatError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except SwarmsplatError as e:
        if args.debug:
            raise
        print(f"swarmsplat {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
