"""The rasteriser against an earlier commit of itself, on this machine, in one run:
`python -m perf.raster_ab [--against COMMIT] [--rounds R] [--kernels warp|taichi] [--json OUT]`.

The default reference is commit 143517d, the rasteriser before its CPU vector kernels (the 4x speed-up target
was set against it). Milliseconds measured on different days come from different machines, so this
checks that commit out into a temporary git worktree and times both trees on the same scenes (perf/raster.py's
`make_scene`, unchanged since then) with the same harness (`perf.raster._ours`: fresh leaf tensors,
`kernels.rasterize`, and for the backward a sum loss; timed by `perf.common.time_fn`, identical in both trees),
alternating one process per tree per round so machine drift falls on both. Reported: per tree the median over
rounds of each process's median, and the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

from .common import CHILD_IMPORTS, tree_env

REFERENCE_COMMIT = "143517d"  # the rasteriser before its CPU vector kernels
CASES = [(640, 480, 50_000), (320, 240, 60_000), (320, 240, 10_000), (160, 120, 1_000)]

_CHILD = CHILD_IMPORTS + r"""
import json, sys
import torch
import importlib, inspect
time_fn = importlib.import_module(perf.__name__ + ".common").time_fn
raster = importlib.import_module(perf.__name__ + ".raster")
make_scene, _ours = raster.make_scene, raster._ours
# the same call in both trees: the reference commit always counted n_touched, so count here too where _ours can opt out
count = {"count": True} if "count" in inspect.signature(_ours).parameters else {}
torch.set_num_threads(1)
kernels.use(backend=sys.argv[1], device="cpu")
out = []
for w, h, n in json.loads(sys.argv[2]):
    sc = make_scene(n, w, h)
    rep = 9 if w * h * n > 5e8 else 25 if n > 1000 else 101
    row = {"image": f"{w}x{h}", "N": n}
    for name, bwd in (("fwd_ms", False), ("fwd_bwd_ms", True)):
        row[name] = time_fn(lambda: _ours(sc, bwd, **count), repeat=rep, warmup=3)["median_s"] * 1e3
    out.append(row)
print("RESULT " + json.dumps(out))
"""


def _time_tree(tree: str, backend: str) -> list[dict]:
    with tempfile.TemporaryDirectory(prefix="swarmsplat-ab-env-") as scratch:
        p = subprocess.run([sys.executable, "-c", _CHILD, backend, json.dumps(CASES)], cwd=tree,
                           env=tree_env(tree, scratch), capture_output=True, text=True, check=False)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode or not lines:
        raise RuntimeError(f"timing {tree} failed (exit {p.returncode}):\n{p.stderr[-2000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def run(against: str, rounds: int, backend: str) -> dict:
    from .common import checkout

    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    head = subprocess.run(["git", "-C", here, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", here, "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, check=True).stdout.strip())
    with checkout(against, "perf.raster_ab") as (_, old):
        runs: dict[str, list] = {"current": [], "against": []}
        for _ in range(rounds):
            runs["against"].append(_time_tree(old, backend))
            runs["current"].append(_time_tree(here, backend))
    rows = []
    for i, (w, h, n) in enumerate(CASES):
        row = {"backend": backend, "image": f"{w}x{h}", "N": n}
        for key in ("fwd_ms", "fwd_bwd_ms"):
            cur = statistics.median(r[i][key] for r in runs["current"])
            ref = statistics.median(r[i][key] for r in runs["against"])
            row[f"{key}"] = round(cur, 3)
            row[f"{key}_{against}"] = round(ref, 3)
            row[f"speedup_{key[:-3]}"] = round(ref / cur, 3)
        rows.append(row)
    return {"subject": "raster-ab", "current": head + ("+changes" if dirty else ""), "against": against,
            "rounds": rounds, "rows": rows, "load_end": os.getloadavg()[0]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.raster_ab", description=__doc__.splitlines()[0])
    p.add_argument("--against", default=REFERENCE_COMMIT)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--kernels", choices=["warp", "taichi"], default="warp")
    p.add_argument("--json", dest="json_out")
    args = p.parse_args(argv)
    load0 = os.getloadavg()[0]
    res = run(args.against, max(1, args.rounds), args.kernels)
    res["load_start"] = load0
    from .common import print_and_save

    print_and_save(res, args.json_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
