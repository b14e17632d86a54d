"""Taichi against Warp on the same rasteriser calls, interleaved in one process:
`python -m perf.backend_ab [--rounds R] [--json OUT]`.

The target: the slower backend within 2x of the faster one at 640x480 / 50k. `python -m perf raster` times
each backend's cases one after the other, so a drift of the machine's speed between them (seen here: the same call
reading 51 and 67 ms a minute apart) lands on one backend only. This alternates the two backends call by call on
the same scenes (perf/raster.py's `make_scene`, the same `_ours` call as perf raster: forward + backward of a sum
loss, count_touched=False), so drift falls on both alike, and reports per backend the median over all rounds and
the ratio of the medians.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

CASES = [(640, 480, 50_000), (320, 240, 60_000), (640, 480, 10_000), (320, 240, 10_000)]
BACKENDS = ("warp", "taichi")


def run(rounds: int) -> dict:
    import torch

    from .common import use_backend
    from .raster import _ours, make_scene

    torch.set_num_threads(1)
    rows = []
    notes = [f"load average at start (1 min, all users): {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"]
    for width, height, n in CASES:
        scene = make_scene(n, width, height)
        times = {b: {"fwd": [], "fwd_bwd": []} for b in BACKENDS}
        for b in BACKENDS:  # warm-up: compile, first page faults
            use_backend(b, "cpu")
            for _ in range(3):
                _ours(scene, True)
        for _ in range(rounds):
            for b in BACKENDS:
                use_backend(b, "cpu")
                for key, bwd in (("fwd", False), ("fwd_bwd", True)):
                    t0 = time.perf_counter()
                    _ours(scene, bwd)
                    times[b][key].append(time.perf_counter() - t0)
        row = {"image": f"{width}x{height}", "N": n, "rounds": rounds}
        for b in BACKENDS:
            for key in ("fwd", "fwd_bwd"):
                row[f"{b}_{key}_ms"] = 1e3 * statistics.median(times[b][key])
        for key in ("fwd", "fwd_bwd"):
            row[f"taichi_over_warp_{key}"] = row[f"taichi_{key}_ms"] / row[f"warp_{key}_ms"]
        rows.append(row)
        print(f"[perf backend_ab] {width}x{height} N={n}: warp {row['warp_fwd_bwd_ms']:.1f} ms, taichi "
              f"{row['taichi_fwd_bwd_ms']:.1f} ms forward+backward ({row['taichi_over_warp_fwd_bwd']:.2f}x)",
              file=sys.stderr, flush=True)
    notes.append(f"load average at end: {os.getloadavg()[0]:.1f}; each round times warp then taichi, forward then "
                 "forward+backward; medians over the rounds; torch intra-op threads 1")
    columns = ["image", "N", "rounds"] + [f"{b}_{k}_ms" for b in BACKENDS for k in ("fwd", "fwd_bwd")] + \
        ["taichi_over_warp_fwd", "taichi_over_warp_fwd_bwd"]
    return {"rows": rows, "columns": columns, "notes": notes}


def main(argv: list[str] | None = None) -> int:
    from .common import print_and_save

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15, help="interleaved rounds per case (default 15)")
    ap.add_argument("--json", dest="json_out", help="write the results as JSON here")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds: expected a positive number")
    res = run(args.rounds)
    print_and_save(res, args.json_out)
    print("\n".join("- " + note for note in res["notes"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
