"""`python -m perf fuzz [--seconds S] [--runs N] [--only NAME,...] [--json OUT] [--md OUT]`: coverage-guided fuzzing
(atheris, libFuzzer) of every parser of outside data in perf/fuzz_targets.py, each in its own process, starting from
its seed corpus (tests/fuzz/corpus/<target>/, copied: the repository's corpus is not grown), with a 1 s limit per
input and 2 GB of memory. A target may only return or raise InputError; anything else is a crash, saved to
tests/fuzz/crashes/<target>/ (the suite replays that folder, tests/test_fuzz_replay.py).

How long: `--seconds S` fuzzes each target for S seconds (default 60); `--runs N` stops each target after N
executions instead (libFuzzer's -runs=N; the seed corpus's own runs count), with `--seconds` then a cap on each
target's time (none unless given). Targets run one after another, one process at a time.

Reported per target: executions, executions per second, coverage (libFuzzer's `cov` and `ft`), the grown corpus,
crashes found, the child's exit status (non-zero: it failed, saved input or not), the seconds it took. Needs
`pip install atheris`.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DESCRIPTION = "coverage-guided fuzzing of the parsers of outside data (atheris)"

_CHILD = r"""
import sys, atheris
from swarmsplat.perf.fuzz_targets import INSTRUMENT, TARGETS, expected_errors, preload
with atheris.instrument_imports(include=INSTRUMENT):
    preload()
target, ok = TARGETS[sys.argv[1]], expected_errors()

def one(data):
    try:
        target(data)
    except ok:
        pass

atheris.Setup([sys.argv[0]] + sys.argv[2:], one)
atheris.Fuzz()
"""


def _stats(log: str) -> dict:
    """The last libFuzzer status line's figures: executions, cov, ft, corpus entries, exec/s."""
    out = {"executions": 0, "cov": None, "ft": None, "corpus": None, "exec_per_s": None}
    for line in log.splitlines():
        m = re.match(r"#(\d+)\s", line)
        if not m:
            continue
        out["executions"] = int(m.group(1))
        for k, pat in (("cov", r"cov: (\d+)"), ("ft", r"ft: (\d+)"), ("corpus", r"corp: (\d+)/"),
                       ("exec_per_s", r"exec/s: (\d+)")):
            f = re.search(pat, line)
            if f:
                out[k] = int(f.group(1))
    return out


def fuzz_one(name: str, seconds: int | None, env: dict, runs: int | None = None) -> dict:
    """Fuzz target `name` for `seconds` (None: no time limit) or `runs` executions (None: no count), whichever
    ends first."""
    from .fuzz_targets import corpus_dir

    limits = [f"-max_total_time={seconds or 0}"] + ([f"-runs={runs}"] if runs else [])

    crashes = corpus_dir(name).parent.parent / "crashes" / name
    with tempfile.TemporaryDirectory(prefix=f"swarmsplat-fuzz-{name}-") as tmp:
        corpus = Path(tmp) / "corpus"
        shutil.copytree(corpus_dir(name), corpus)
        art = Path(tmp) / "artifacts"
        art.mkdir()
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", _CHILD, name, str(corpus), *limits,
                            "-timeout=1", "-rss_limit_mb=2048", f"-artifact_prefix={art}/", "-print_final_stats=1"],
                           capture_output=True, text=True, env=env, check=False,
                           timeout=seconds + 120 if seconds else None)
        wall = time.perf_counter() - t0
        found = sorted(art.iterdir())
        if found:
            crashes.mkdir(parents=True, exist_ok=True)
            for f in found:
                shutil.copy(f, crashes / f.name)
        st = _stats(p.stderr)
        # a child that ended badly without saving its input (e.g. killed while reporting a crash) says so too
        why = next((ln for ln in p.stderr.splitlines() if "Error" in ln or "Traceback" in ln), "") or \
            f"exit {p.returncode}: {' | '.join(p.stderr.strip().splitlines()[-2:])}"
        return {"target": name, **st, "seconds": round(wall, 1), "exit": p.returncode,
                "crashes": [f.name for f in found], "first_crash": why if found or p.returncode else ""}


def main(argv: list[str] | None = None) -> int:
    from .common import machine_info, markdown_table, write_results
    from .fuzz_targets import TARGETS

    p = argparse.ArgumentParser(prog="python -m perf fuzz", description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=int, help="fuzzing time per target (default 60; with --runs, a cap)")
    p.add_argument("--runs", type=int, help="stop each target after this many executions (libFuzzer -runs)")
    p.add_argument("--only", help="comma-separated targets (default: all): " + ", ".join(TARGETS))
    p.add_argument("--json", dest="json_out")
    p.add_argument("--md", dest="md_out")
    args = p.parse_args(argv)
    names = args.only.split(",") if args.only else list(TARGETS)
    bad = [n for n in names if n not in TARGETS]
    if bad:
        p.error(f"unknown target(s) {', '.join(bad)}; choose from {', '.join(TARGETS)}")
    try:
        import atheris  # noqa: F401
    except ImportError:
        p.error("needs atheris: pip install atheris")
    if args.runs is not None and args.runs < 1:
        p.error(f"--runs must be at least 1, got {args.runs}")
    if args.seconds is not None and args.seconds < 1:
        p.error(f"--seconds must be at least 1, got {args.seconds}")
    seconds = args.seconds if args.seconds or args.runs else 60
    env = dict(os.environ)
    rows = []
    for n in names:
        r = fuzz_one(n, seconds, env, args.runs)
        rows.append(r)
        print(f"[fuzz] {n}: {r['executions']} executions, cov {r['cov']}, {len(r['crashes'])} crashes", file=sys.stderr)
    cols = ["target", "executions", "exec_per_s", "cov", "ft", "corpus", "crashes", "exit", "seconds"]
    limit = " or ".join(([f"{args.runs} executions"] if args.runs else []) + ([f"{seconds} s"] if seconds else []))
    limit += ", whichever came first" if args.runs and seconds else ""
    report = {"subject": "fuzz", "machine": machine_info(), "seconds_per_target": seconds,
              "runs_per_target": args.runs, "rows": rows}
    md = (f"# fuzz\n\n{DESCRIPTION}; each target until {limit}.\n\n"
          + markdown_table([{**r, "crashes": len(r["crashes"])} for r in rows], cols) + "\n")
    print(json.dumps(rows, indent=1))
    write_results(args.json_out, args.md_out, report, md)
    return 1 if any(r["crashes"] or r["exit"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
