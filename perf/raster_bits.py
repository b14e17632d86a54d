"""Does a change to the rasteriser keep every output bit for bit? `python -m perf.raster_bits [--against COMMIT]
[--kernels warp|taichi] [--json OUT]`.

Renders four scenes (perf/raster.py's `make_scene`: 160x120 / 1k, 320x240 / 20k and 60k, 640x480 / 10k) with
hit counts and a viewmat that needs a gradient, backpropagates a fixed loss, and compares colour, depth,
depth / alpha, alpha, the hit counts and the gradients of the means, quats, scales, opacities, colours and viewmat
between this tree and a temporary git worktree of COMMIT (default HEAD: what the uncommitted changes do). Each
tree runs in its own process. Exit status 0 when every output is equal (torch.equal), 1 otherwise; the table
gives each output's largest difference. Code that is meant to change no result (the Warp compositing module
contracts multiply-adds, so a change of code shape can move roundings) is checked with this before it is kept.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

from .common import CHILD_IMPORTS, tree_env

CASES = [(160, 120, 1_000, 0), (320, 240, 20_000, 3), (320, 240, 60_000, 5), (640, 480, 10_000, 7)]
NAMES = ["color", "depth", "depth_normalised", "alpha", "n_touched", "g_means", "g_quats", "g_scales",
         "g_opacities", "g_colors", "g_viewmat"]

_CHILD = CHILD_IMPORTS + r"""
import json, sys
import torch
import importlib
raster = importlib.import_module(perf.__name__ + ".raster")
_loss, _params, make_scene = raster._loss, raster._params, raster.make_scene
torch.set_num_threads(1)
kernels.use(backend=sys.argv[1], device="cpu")
out = []
for w, h, n, seed in json.loads(sys.argv[2]):
    sc = make_scene(n, w, h, seed=seed)
    p = _params(sc, True)
    p["viewmat"] = sc["viewmat"].clone().requires_grad_(True)
    o = kernels.rasterize(**p)
    _loss(o.color, o.depth, o.alpha).backward()
    out.append([t.detach() for t in (o.color, o.depth, o.depth_normalised, o.alpha, o.n_touched)]
               + [p[k].grad for k in ("means", "quats", "scales", "opacities", "colors", "viewmat")])
torch.save(out, sys.argv[3])
"""


def _outputs(tree: str, backend: str, path: str) -> list:
    import json

    import torch

    env = tree_env(tree, os.path.dirname(path) + "/" + os.path.basename(tree))
    p = subprocess.run([sys.executable, "-c", _CHILD, backend, json.dumps(CASES), path], cwd=tree, env=env,
                       capture_output=True, text=True, check=False)
    if p.returncode:
        raise RuntimeError(f"rendering in {tree} failed (exit {p.returncode}):\n{p.stderr[-2000:]}")
    return torch.load(path)


def run(against: str, backend: str) -> dict:
    from .common import checkout

    with checkout(against, "perf.raster_bits") as (here, old), tempfile.TemporaryDirectory() as tmp:
        cur = _outputs(here, backend, os.path.join(tmp, "current.pt"))
        ref = _outputs(old, backend, os.path.join(tmp, "against.pt"))
    rows = []
    for (w, h, n, _seed), a, b in zip(CASES, cur, ref):
        for name, x, y in zip(NAMES, a, b):
            rows.append({"image": f"{w}x{h}", "N": n, "output": name, "equal": bool(x.equal(y)),
                         "max_abs_diff": float((x.double() - y.double()).abs().max()) if x.numel() else 0.0})
    return {"subject": "raster-bits", "backend": backend, "against": against,
            "all_equal": all(r["equal"] for r in rows), "rows": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.raster_bits", description=__doc__.splitlines()[0])
    p.add_argument("--against", default="HEAD")
    p.add_argument("--kernels", choices=["warp", "taichi"], default="warp")
    p.add_argument("--json", dest="json_out")
    args = p.parse_args(argv)
    res = run(args.against, args.kernels)
    from .common import print_and_save

    print_and_save(res, args.json_out)
    print(f"[perf raster_bits] {'every output equal' if res['all_equal'] else 'OUTPUTS DIFFER'} "
          f"({args.kernels}, this tree against {args.against})", file=sys.stderr)
    return 0 if res["all_equal"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
