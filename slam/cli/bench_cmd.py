"""`swarmsplat bench SUBJECT ...`: the perf/ driver, from the console script."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bench", help="run perf/ benchmarks (same flags as `python -m perf`)", add_help=False)
    p.add_argument("-h", "--help", action="store_true", help="perf's own help")
    p.add_argument("rest", nargs="...", help="arguments for `python -m perf`")
    p.set_defaults(func=run)


def run(args) -> int:
    import argparse

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_file
    from swarmsplat.perf.__main__ import main as perf_main

    for flag in ("--json", "--md"):  # an unwritable output fails before the benchmarks run, not after
        for i, a in enumerate(args.rest):
            path = args.rest[i + 1] if a == flag and i + 1 < len(args.rest) else \
                (a.split("=", 1)[1] if a.startswith(flag + "=") else None)
            if path:
                output_file(path, flag, create=False)

    class OneLineParser(argparse.ArgumentParser):  # the package's one-line error instead of usage + error
        def error(self, message):
            raise InputError(f"{message} (see swarmsplat bench --help)")

    return perf_main(["--help"] if args.help else args.rest, prog="swarmsplat bench", parser_class=OneLineParser)
