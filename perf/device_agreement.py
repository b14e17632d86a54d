"""Every backend/device pair on the same work: the rasteriser at a working size, and a real RGB-D run.

`python -m perf.device_agreement [--device vulkan] [--frames 60] [--data DIR] [--skip-raster] [--skip-real]`

1. raster: 320x240 with 60k Gaussians (perf/raster.py's scene), forward and forward+backward on taichi-cpu and on
   taichi-<device>: median times, and the device's colour / depth / gradients against taichi-cpu's;
2. real: `swarmsplat run DATA --frames N` on warp-cpu, taichi-cpu and taichi-<device> (one subprocess each, with
   the run's own device self-check): ATE RMSE and PSNR of each, and whether they agree with warp-cpu's within
   ATE_REL (relative) and PSNR_DB.

Writes perf/results/device-agreement-<device>.{json,md} (perf.common.write_results: commit, date, machine,
versions). `python -m perf device-check` runs part 2 too; tests/test_device_agreement.py runs part 2 with fewer
frames. Exit status 1 when a pair disagrees or a run fails.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "redwood_livingroom1_211"
ATE_REL = 0.02  # ATE RMSE within 2 % of warp-cpu's
PSNR_DB = 0.3  # PSNR within 0.3 dB of warp-cpu's
CLI = "import sys; from swarmsplat.slam.cli import main; sys.exit(main(sys.argv[1:]))"  # `swarmsplat`, this Python


def pairs_for(device: str) -> list[tuple[str, str]]:
    """warp-cpu (the reference), taichi-cpu, and the device's pairs (Warp has no Vulkan)."""
    extra = [("taichi", device)] if device == "vulkan" else [("warp", device), ("taichi", device)]
    return [("warp", "cpu"), ("taichi", "cpu")] + ([] if device == "cpu" else extra)


def run_real(data: str | Path, frames: int, pairs: list[tuple[str, str]], timeout: float = 7200.0,
             ate_floor_m: float = 0.0, settings: list[str] = ()) -> dict:
    """`swarmsplat run DATA --frames N --kernels B --device D [--set S ...]` per pair, each in its own interpreter.
    Returns {"rows": [{pair, status, ate_rmse, psnr, gaussians, seconds, error?}], "agree": bool, "reasons": [...]},
    each row compared with the first pair's (warp-cpu); ate_floor_m: see `agreement`; settings: `--set` items."""
    rows = []
    for backend, device in pairs:
        with tempfile.TemporaryDirectory(prefix="swarmsplat-agree-") as tmp:
            cmd = [sys.executable, "-c", CLI, "run", str(data), "--frames", str(frames),
                   "--kernels", backend, "--device", device, "--out", tmp, "--quiet"]
            cmd += [a for item in settings for a in ("--set", item)]
            print(f"[device-agreement] {backend}-{device}: {frames} frames of {Path(data).name}", file=sys.stderr,
                  flush=True)
            t0 = time.perf_counter()
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
            except subprocess.TimeoutExpired:
                rows.append({"pair": f"{backend}-{device}", "status": "timeout", "error": f"over {timeout:.0f} s"})
                continue
            row = {"pair": f"{backend}-{device}", "seconds": round(time.perf_counter() - t0, 1)}
            metrics = Path(tmp) / "metrics.json"
            if proc.returncode == 0 and metrics.exists():
                m = json.loads(metrics.read_text())
                row.update(status=m["status"], ate_rmse=m.get("ate_rmse"), psnr=m.get("psnr"),
                           gaussians=m.get("gaussians"), run_s=m["time_s"]["total"], warnings=m.get("warnings"))
            else:
                row.update(status="error", error=" ".join((proc.stderr or proc.stdout).split())[-400:])
            rows.append(row)
    return {"frames": frames, "data": str(data), "rows": rows, **agreement(rows, ate_floor_m)}


def agreement(rows: list[dict], ate_floor_m: float = 0.0) -> dict:
    """Each row against the first: status complete, ATE within ATE_REL of it (or within ate_floor_m metres, when
    that is larger: over a few frames the ATE is ~1 mm and the backends' float32 rounding alone moves it by a few
    hundredths of a millimetre), PSNR within PSNR_DB."""
    reasons = []
    ref = rows[0] if rows else {}
    for r in rows:
        if r.get("status") != "complete":
            reasons.append(f"{r['pair']}: {r.get('status')} ({r.get('error', '')})")
            continue
        if r is ref:
            continue
        r["ate_rel_diff"] = abs(r["ate_rmse"] - ref["ate_rmse"]) / ref["ate_rmse"]
        r["psnr_diff_db"] = r["psnr"] - ref["psnr"]
        if abs(r["ate_rmse"] - ref["ate_rmse"]) > max(ATE_REL * ref["ate_rmse"], ate_floor_m):
            reasons.append(f"{r['pair']}: ATE {r['ate_rmse']:.5f} m vs {ref['ate_rmse']:.5f} m "
                           f"({100 * r['ate_rel_diff']:.1f} % > {100 * ATE_REL:.0f} %"
                           + (f" and > {1e3 * ate_floor_m:.2f} mm)" if ate_floor_m else ")"))
        if abs(r["psnr_diff_db"]) > PSNR_DB:
            reasons.append(f"{r['pair']}: PSNR {r['psnr']:.2f} dB vs {ref['psnr']:.2f} dB "
                           f"({r['psnr_diff_db']:+.2f} dB, bound {PSNR_DB} dB)")
    return {"agree": not reasons and bool(rows), "reasons": reasons}


def run_raster(device: str, repeat: int = 3) -> dict:
    """320x240 / 60k Gaussians: taichi-cpu and taichi-<device>, times and the device against the CPU."""
    import torch

    from swarmsplat import kernels

    from .common import time_fn
    from .raster import _loss, make_scene

    scene = make_scene(60_000, 320, 240)
    res, rows = {}, []

    def fwd_bwd(keep=None):
        p = {k: scene[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
        vm = scene["viewmat"].clone().requires_grad_(True)
        o = kernels.rasterize(**{**scene, **p, "viewmat": vm})
        _loss(o.color, o.depth, o.alpha).backward()
        if keep is not None:
            keep.update(o=o, grads={k: v.grad for k, v in p.items()} | {"viewmat": vm.grad})

    for device_ in ("cpu", device):
        kernels.use("taichi", device_)
        fwd_bwd()  # compile / load
        f = time_fn(lambda: kernels.rasterize(**scene), repeat=repeat, warmup=1)
        fb = time_fn(fwd_bwd, repeat=repeat, warmup=0)
        keep: dict = {}
        fwd_bwd(keep)
        res[device_] = keep
        rows.append({"pair": f"taichi-{device_}", "image": "320x240", "N": 60_000, "fwd_ms": 1e3 * f["median_s"],
                     "fwd_bwd_ms": 1e3 * fb["median_s"]})
    a, b = res["cpu"]["o"], res[device]["o"]
    diff = {k: float((getattr(a, k) - getattr(b, k)).detach().abs().max()) for k in ("color", "depth", "alpha")}
    grads = {k: float((g - res[device]["grads"][k]).norm() / g.norm()) for k, g in res["cpu"]["grads"].items()}
    rows[1].update({f"max_{k}_diff": v for k, v in diff.items()})
    rows[1]["max_grad_rel_diff"] = max(grads.values())
    rows[1]["n_touched_differ"] = int((a.n_touched != b.n_touched).sum())
    kernels.use("warp", "cpu")
    return {"rows": rows, "gradient_rel_diff": grads,
            "note": "the device against taichi-cpu: max per-pixel differences, relative L2 error of each gradient; "
                    "tests/test_vulkan.py holds them to bounds, with the pixels where rounding decides a 1/255 "
                    "cut-off set apart"}


def markdown(report: dict) -> str:
    from .common import markdown_table

    out = []
    if "raster" in report:
        out += ["## Rasteriser, 320x240 with 60k Gaussians (perf/raster.py's scene)", "",
                markdown_table(report["raster"]["rows"], ["pair", "image", "N", "fwd_ms", "fwd_bwd_ms",
                                                          "max_color_diff", "max_depth_diff", "max_grad_rel_diff",
                                                          "n_touched_differ"]), ""]
    if "real" in report:
        r = report["real"]
        out += [f"## {Path(r['data']).name}, first {r['frames']} frames: `swarmsplat run` per pair", "",
                markdown_table(r["rows"], ["pair", "status", "ate_rmse", "ate_rel_diff", "psnr", "psnr_diff_db",
                                           "gaussians", "run_s"]), "",
                f"Agreement with warp-cpu (ATE within {100 * ATE_REL:.0f} %, PSNR within {PSNR_DB} dB): "
                + ("yes" if r["agree"] else "NO: " + "; ".join(r["reasons"])), ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.device_agreement", description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=["cpu", "cuda", "vulkan"], default="vulkan")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--data", default=str(DATA))
    p.add_argument("--skip-raster", action="store_true")
    p.add_argument("--skip-real", action="store_true")
    p.add_argument("--json", dest="json_out", help="default perf/results/device-agreement-<device>.json")
    p.add_argument("--md", dest="md_out", help="default perf/results/device-agreement-<device>.md")
    args = p.parse_args(argv)

    from .common import machine_info, write_results

    report: dict = {"machine": machine_info(), "device": args.device}
    if not args.skip_raster and args.device != "cpu":
        report["raster"] = run_raster(args.device)
    if not args.skip_real:
        report["real"] = run_real(args.data, args.frames, pairs_for(args.device))
    stem = REPO / "perf" / "results" / f"device-agreement-{args.device}"
    md = markdown(report)
    print(md)
    write_results(args.json_out or f"{stem}.json", args.md_out or f"{stem}.md", report, md)
    return 0 if report.get("real", {}).get("agree", True) else 1


if __name__ == "__main__":
    sys.exit(main())
