"""`swarmsplat bench SUBJECT ...`: the perf/ driver, from the console script."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bench", help="run perf/ benchmarks (same flags as `python -m perf`)", add_help=False)
    p.add_argument("rest", nargs="...", help="arguments for `python -m perf`")
    p.set_defaults(func=run)


def run(args) -> int:
    import argparse
    from unittest import mock

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_file
    from swarmsplat.perf.__main__ import main as perf_main

    for flag in ("--json", "--md"):  # an unwritable output fails before the benchmarks run, not after
        for i, a in enumerate(args.rest):
            path = args.rest[i + 1] if a == flag and i + 1 < len(args.rest) else \
                (a.split("=", 1)[1] if a.startswith(flag + "=") else None)
            if path:
                output_file(path, flag, create=False)

    def one_line(parser, message):  # perf's own parser: the package's one-line error instead of usage + error
        raise InputError(f"{message} (see swarmsplat bench --help)")

    with mock.patch.object(argparse.ArgumentParser, "error", one_line):
        return perf_main(args.rest)
