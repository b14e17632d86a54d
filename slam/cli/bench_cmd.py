"""`swarmsplat bench SUBJECT ...`: the perf/ driver, from the console script; `swarmsplat devices`: the kernel
backend/device pairs of this machine and their self-check."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("bench", help="run perf/ benchmarks (same flags as `python -m perf`)", add_help=False)
    p.add_argument("-h", "--help", action="store_true", help="perf's own help")
    p.add_argument("rest", nargs="...", help="arguments for `python -m perf`")
    p.set_defaults(func=run)
    register_devices(sub)


def register_devices(sub) -> None:
    p = sub.add_parser("devices", help="the kernel backend/device pairs that load here, each with its self-check "
                                       "(a probe render against the twin, as a run does before its first frame)")
    p.add_argument("--size", default="320x240", help="probe size WIDTHxHEIGHT in pixels (a run uses its working "
                                                     "size; default 320x240)")
    p.add_argument("--no-check", action="store_true", help="only list the pairs whose runtime loads")
    p.set_defaults(func=run_devices)


def run_devices(args) -> int:
    """One line per pair; exit 1 when a pair that loads fails its self-check."""
    from swarmsplat import kernels
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.selfcheck import check_all

    try:
        w, h = (int(x) for x in args.size.lower().split("x"))
        assert w > 0 and h > 0
    except (ValueError, AssertionError):
        raise InputError(f"--size: expected WIDTHxHEIGHT, e.g. 320x240, got {args.size!r}") from None
    found = kernels.devices()
    if args.no_check:
        for b in found:
            print(f"{b.name}-{b.device}")
        return 0
    results = check_all(w, h, found)
    for r in results:
        print(r.line(), flush=True)
    return 0 if all(r.ok for r in results) else 1


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
