"""`python -m perf SUBJECT [--kernels warp|taichi] [--device cpu|cuda|vulkan] [--quick] [--json OUT] [--md OUT]`.

Runs one benchmark subject (or `all`), prints a Markdown table and writes JSON with the machine's description.
Runs unchanged on a GPU machine with `--device cuda` (vulkan: Taichi only). `python -m perf device-check` runs
the suite's device cases and a quick benchmark of every subject on one device (perf/device_check.py);
`python -m perf realtime` replays a real sequence in real-time mode (perf/realtime.py); `python -m perf soak
--minutes M` runs a team of agent processes under random faults (perf/soak.py).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

from .common import machine_info, markdown_table, write_results

# subject name -> module; modules that do not exist (yet) are skipped by `all` and reported by name.
SUBJECTS = {
    "generator": ".generator",
    "raster": ".raster",
    "mapping": ".mapping",
    "icp": ".icp",
    "graph": ".graph",
    "graph-benchmarks": ".graph_benchmarks",
    "frontend": ".frontend",
    "slam": ".slam",
    "tracking-refine": ".tracking_refine",
    "fig5": ".flocc_fig5",
    "loops-real": ".loops_real",
    "realpairs": ".real_pairs",
    "placerec": ".place_recognition",
    "bags": ".bags",
    "live": ".live",
    "live-team": ".live_team",
    "long-run": ".long_run",
    "loop-graph": ".loop_graph",
    "distributed": ".distributed",
    "distributed-processes": ".distributed_processes",
    "team-scale": ".team_scale",
    "wide-joins": ".wide_joins",
    "wide-joins-hololens": ".wide_joins_hololens",
    "map-quality": ".map_quality",
}


def _load(name: str):
    try:
        return importlib.import_module(SUBJECTS[name], __package__)
    except ModuleNotFoundError as e:
        if e.name == __package__ + SUBJECTS[name]:
            return None
        raise


def main(argv: list[str] | None = None, *, prog: str = "python -m perf",
         parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser) -> int:
    """The driver. `prog` and `parser_class` let another front end (`swarmsplat bench`) name itself in usage and
    turn usage errors into its own."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["device-check"]:
        from .device_check import main as device_check

        return device_check(argv[1:], prog=f"{prog} device-check", parser_class=parser_class)
    if argv[:1] == ["realtime"]:  # its own flags and result files (perf/realtime.py)
        from .realtime import main as realtime

        return realtime(argv[1:])
    if argv[:1] == ["fuzz"]:  # its own flags: seconds per target, targets (perf/fuzz.py)
        from .fuzz import main as fuzz

        return fuzz(argv[1:])
    if argv[:1] == ["soak"]:  # its own flags: minutes, seed, fault kinds (perf/soak.py)
        from .soak import main as soak

        return soak(argv[1:])
    if argv[:1] == ["team-link"]:  # its own flags and result files (perf/team_link.py)
        from .team_link import main as team_link

        return team_link(argv[1:])
    p = parser_class(prog=prog, description=__doc__.splitlines()[0])
    p.add_argument("subject", choices=sorted(SUBJECTS) + ["all"])
    p.add_argument("--kernels", choices=["warp", "taichi", "both"], default="both")
    p.add_argument("--device", choices=["cpu", "cuda", "vulkan"], default="cpu", help="vulkan: Taichi only")
    p.add_argument("--quick", action="store_true", help="smaller sizes and fewer repeats")
    p.add_argument("--json", dest="json_out", help="write results as JSON here")
    p.add_argument("--md", dest="md_out", help="write the Markdown tables here")
    args = p.parse_args(argv)

    from swarmsplat.kernels.errors import SwarmsplatError

    names = sorted(SUBJECTS) if args.subject == "all" else [args.subject]
    backends = ["warp", "taichi"] if args.kernels == "both" else [args.kernels]
    if args.device == "vulkan" and args.kernels == "both":
        backends = ["taichi"]  # Warp has no Vulkan backend
    report = {"machine": machine_info(), "device": args.device, "quick": args.quick,
              "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "subjects": {}}
    md = []
    for name in names:
        mod = _load(name)
        if mod is None:
            print(f"[perf] subject {name!r} is not available in this checkout; skipped", file=sys.stderr)
            continue
        print(f"[perf] {name}: {mod.DESCRIPTION}", file=sys.stderr)
        try:
            res = mod.run(backends=backends, device=args.device, quick=args.quick)
        except SwarmsplatError as e:
            print(f"[perf] {name}: error: {e}", file=sys.stderr)
            return e.exit_code
        report["subjects"][name] = res
        table = markdown_table(res["rows"], res["columns"])
        md.append(f"### {name}\n\n{mod.DESCRIPTION}\n\n{table}\n" + "".join(f"\n- {n}" for n in res.get("notes", [])))
        print(md[-1])
    write_results(args.json_out, args.md_out, report, "\n\n".join(md))
    if args.json_out:
        print(f"[perf] wrote {args.json_out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
