"""The package's headline figures, each from one whole command as a user runs it, with its provenance:
`python -m perf.end_to_end [--only demo|redwood-211] [--out-dir perf/results]`.

  demo         `swarmsplat demo --out DIR --quiet`: generates the 3-agent dataset, runs the team, evaluates
  redwood-211  `swarmsplat run ../shared/data/redwood_livingroom1_211 --out DIR --quiet`: one agent on real data

Each command runs in its own process; the figures are its metrics.json (accuracy, rendering, loops) plus its wall
time, CPU time and peak resident memory (the process's own rusage). The peer in the same run is the command's
own tracking-only trajectory (ATE without loop closure), which metrics.json reports beside the final one.
Writes `<name>-cpu.json` and `<name>-cpu.md` with commit, date, CPU, load and library versions.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import machine_info, markdown_table, write_results

REPO = Path(__file__).resolve().parents[1]
REDWOOD = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", REPO.parent / "shared" / "data")) / \
    "redwood_livingroom1_211"

# name -> (command after `swarmsplat`, metrics.json path inside the output folder, figures to report)
RUNS = {
    "demo": (["demo", "--out", "{out}", "--quiet"], "results/metrics.json",
             ["ate_rmse_team", "ate_rmse_team_agents", "all_agents_joined", "psnr", "ssim", "depth_l1",
              "psnr_novel", "ssim_novel", "render_resolution", "gaussians", "loops_accepted", "loop_candidates"]),
    "redwood-211": (["run", str(REDWOOD), "--out", "{out}", "--quiet"], "metrics.json",
                    ["ate_rmse", "ate_rmse_no_lc", "psnr_merged", "ssim_merged", "depth_l1_merged",
                     "psnr_merged_input_resolution", "render_resolution", "input_resolution", "frames",
                     "keyframes", "gaussians", "loops_accepted", "loop_candidates", "fps"]),
}


def run_one(name: str, scratch: str) -> dict:
    args, metrics_path, keys = RUNS[name]
    out = os.path.join(scratch, name)
    cmd = [sys.executable, "-m", "swarmsplat.slam", *(a.format(out=out) for a in args)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read() if proc.stderr else ""
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}):\n{err[-2000:]}")
    metrics = json.loads(Path(out, metrics_path).read_text())
    shown = " ".join(["swarmsplat", *(a.format(out="DIR") for a in args)]).replace(str(REPO.parent), "..")
    return {"name": name, "command": shown, "wall_s": round(wall, 1),
            "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
            "figures": {k: metrics.get(k) for k in keys}, "status": metrics.get("status")}


def _shown(key: str, v) -> str:
    """A figure as a reader wants it: ATE and depth L1 in cm, PSNR in dB, the rest as they are."""
    if isinstance(v, float) and (key.startswith("ate_rmse") or key.startswith("depth_l1")):
        return f"{100 * v:.3f} cm"
    if isinstance(v, float) and key.startswith("psnr"):
        return f"{v:.2f} dB"
    if isinstance(v, float):
        return f"{v:.1f}" if key.endswith(("_s", "_mb")) or abs(v) >= 100 else f"{v:.3f}"
    return ", ".join(map(str, v)) if isinstance(v, list) else str(v)


def markdown(res: dict) -> str:
    rows = [{"figure": k, "value": _shown(k, v)} for k, v in res["figures"].items()]
    rows += [{"figure": k, "value": _shown(k, float(res[k]))} for k in ("wall_s", "cpu_s", "peak_rss_mb")]
    return f"### {res['name']}\n\n`{res['command']}`\n\n{markdown_table(rows, ['figure', 'value'])}\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.end_to_end", description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=sorted(RUNS), action="append", help="run only this one (repeatable)")
    p.add_argument("--out-dir", default=str(REPO / "perf" / "results"), help="where the result files go")
    p.add_argument("--from-json", action="store_true", help="only write the Markdown again from the JSON files")
    args = p.parse_args(argv)
    if args.from_json:
        for name in args.only or list(RUNS):
            base = os.path.join(args.out_dir, f"{name}-cpu")
            with open(base + ".json") as f:
                res = json.load(f)
            write_results(None, base + ".md", res, markdown(res))  # the JSON's own machine record heads it
        return 0
    names = args.only or list(RUNS)
    if "redwood-211" in names and not REDWOOD.is_dir():
        raise SystemExit(f"python -m perf.end_to_end: {REDWOOD} not found (set SWARMSPLAT_SHARED_DATA)")
    with tempfile.TemporaryDirectory(prefix="swarmsplat-e2e-") as scratch:
        for name in names:
            print(f"[end_to_end] {name} ...", file=sys.stderr, flush=True)
            machine = machine_info()  # where and from what, as the run starts
            res = {**run_one(name, scratch), "machine": machine}
            md = markdown(res)
            print(md)
            base = os.path.join(args.out_dir, f"{name}-cpu")
            write_results(base + ".json", base + ".md", res, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
