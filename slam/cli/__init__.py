"""The `swarmsplat` console script: a thin layer of subcommands over keyword-argument library functions.

Each subcommand lives in its own module `slam/cli/<name>_cmd.py` exposing
    register(subparsers) -> None   # adds its parser and sets `func=run` as the default
    run(args) -> int               # translates the namespace into explicit keyword arguments
Heavy imports happen inside `run`. SwarmsplatError subclasses become one line on stderr and their exit code.
"""

from __future__ import annotations

import argparse
import importlib
import os
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
    "agent_cmd",
    "ros_cmd",
    "bench_cmd",
    "view_cmd",
]


def add_backend_flags(p: argparse.ArgumentParser) -> None:
    """--kernels / --device, shared by every subcommand that launches kernels."""
    p.add_argument("--kernels", choices=["warp", "taichi"], default="warp", help="kernel backend (default: warp)")
    p.add_argument("--device", choices=["cpu", "cuda", "vulkan"], default="cpu",
                   help="kernel device (default: cpu; vulkan: --kernels taichi only)")


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are the package's one line: `swarmsplat run: error: ...` (exit 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> str:
    return f"swarmsplat: warning: {message}\n"


def version() -> str:
    """The installed distribution's version ("unknown" when run from a checkout that is not installed)."""
    from importlib import metadata

    try:
        return metadata.version("swarmsplat")
    except metadata.PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="swarmsplat",
        description="Collaborative multi-robot SLAM: GRAND-SLAM (RGB-D Gaussian splatting) and FLOCC-SLAM loop closing.",
    )
    parser.add_argument("--version", action="version", version=f"swarmsplat {version()}")
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


def _end_now(code: int) -> None:
    """The console script after an interrupt or a failure: everything worth keeping is written (atomically), so
    end here — no interpreter teardown (seconds of garbage collection over a big map) and no thread may delay it."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand. Exit codes: 0 done, 2 bad input (one line on stderr), 130 interrupted (SIGINT / SIGTERM;
    a second one exits at once), 1 failed; an interrupted or failed run has written what it had (slam.run.guard).
    argv None (the console script, `python -m swarmsplat.slam`): after an interrupt or an unexpected failure the process
    ends at once (`_end_now`), whatever thread is still running."""
    import warnings

    from swarmsplat.kernels.errors import SwarmsplatError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    name = f"swarmsplat {args.command}"
    previous_format = warnings.formatwarning
    warnings.formatwarning = _one_line_warning
    try:
        return int(args.func(args) or 0)
    except SwarmsplatError as e:
        if args.debug:
            raise
        print(f"{name}: error: {e}", file=sys.stderr)
        if argv is None:
            _end_now(e.exit_code)
        return e.exit_code
    except OSError as e:  # a file the checks could not foresee (disk full, permissions changed mid-run)
        if args.debug:
            raise
        path = e.filename2 or e.filename  # os.replace(tmp, path): the path the user named is the second
        where = f": {path}" if path else ""
        print(f"{name}: error: {e.strerror or e}{where}", file=sys.stderr)
        if argv is None:
            _end_now(1)
        return 1
    except KeyboardInterrupt as e:
        print(f"{name}: interrupted ({e or 'KeyboardInterrupt'})", file=sys.stderr)
        if argv is None:
            _end_now(130)
        return 130
    except Exception:
        if argv is not None or args.debug:  # called from Python: the caller sees the exception itself
            raise
        import traceback

        traceback.print_exc()
        print(f"{name}: failed (the traceback above is a bug; please report it)", file=sys.stderr)
        _end_now(1)
    finally:
        warnings.formatwarning = previous_format


if __name__ == "__main__":
    sys.exit(main())
