"""Real-time mode on a real sequence: Redwood living room 1 (211 frames, 640x480) replayed at 15 and 30 Hz
(`swarmsplat run --realtime --rate HZ`, with the default settings and with configs/realtime.yaml's cheaper
tracker) against the offline run of the same frames in the same process.

Per run: frames tracked (%), dropped and why, pose latency from a frame's arrival to its pose (p50 / p95 / max),
the tracker's step time, mapping iterations per keyframe, the CPU time of the tracking and mapping threads over
the stream (their sum above the stream's wall time means they ran at the same time), the ATE of the poses as
emitted and after the run (loop closures, map refinement), and the merged map's PSNR; the offline run's ATE and
PSNR beside them. The machine's 1-minute load average is recorded before and after each run: other processes on
the same cores lengthen every latency.

    python -m perf realtime                      # -> perf/results/realtime-cpu.{json,md} (3.5-5 min, shared 2 cores)
    python -m perf realtime --rates 15 --presets realtime --no-offline
    python -m perf realtime --from-json          # rewrite perf/results/realtime-cpu.md from its JSON
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from .common import machine_info, markdown_table, write_results

DESCRIPTION = "real-time replay of Redwood 211 at 15 and 30 Hz: tracked %, pose latency, ATE and PSNR vs offline"

ROOT = Path(__file__).resolve().parents[1]
REDWOOD = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", ROOT.parent / "shared" / "data")) / "redwood_livingroom1_211"
RESULTS = ROOT / "perf" / "results"
TARGETS = {15.0: 66.0, 30.0: 33.0}  # rate (Hz) -> the pose latency p95 to reach (ms)


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def measure(data: Path, rate: float | None, preset: str | None) -> dict:
    """One run (rate None: offline) in this process; its figures."""
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.realtime.run import run_realtime
    from swarmsplat.slam.run.sequence import run_sequence

    cfg = SlamConfig.preset(preset) if preset else SlamConfig()
    load0 = _load()
    with tempfile.TemporaryDirectory(prefix="swarmsplat-rt-") as out:
        t0 = time.perf_counter()
        if rate is None:
            m = run_sequence(data, out, cfg.override({"runtime": {"realtime": False}}), progress=False)
        else:
            m = run_realtime(data, out, cfg.override({"runtime": {"realtime": True, "rate": rate}}), progress=False)
        wall = time.perf_counter() - t0
    row = {"mode": "offline" if rate is None else "real time", "rate_hz": rate, "preset": preset or "defaults",
           "ate_cm": 100 * m["ate_rmse"], "psnr_merged_db": m["psnr_merged"], "keyframes": m["keyframes"],
           # held-out frames (never a keyframe nor a late view): the two runs' keyframes differ, these less so
           "psnr_novel_db": m.get("psnr_novel"), "psnr_submaps_db": m.get("psnr"),
           "wall_s": wall, "load_before": load0, "load_after": _load()}
    r = m.get("realtime")
    if r:
        lat, step = r["pose_latency_ms"], r["step_ms"]
        row.update({"tracked_pct": 100 * r["tracked_fraction"], "frames_tracked": r["frames_tracked"],
                    "dropped": r["frames_dropped"],
                    "dropped_by_reason": r["dropped_by_reason"], "latency_p50_ms": lat["p50"],
                    "latency_p95_ms": lat["p95"], "latency_max_ms": lat["max"], "step_p50_ms": step["p50"],
                    "step_p95_ms": step["p95"], "ate_live_cm": 100 * r["ate_rmse_live"],
                    "mapping_iterations_mean": r["mapping_iterations"]["mean"],
                    "keyframes_deferred": r["keyframes_deferred"], "late_views": r.get("late_views", 0),
                    "psnr_late_views_db": m.get("psnr_late_views"), "stream_s": r["stream_s"],
                    "refinements_skipped": r.get("refinements_skipped", 0),
                    "cpu_tracker_s": r["cpu_s"]["tracker_thread"], "cpu_mapping_s": r["cpu_s"]["mapping_thread"],
                    "cpu_process_s": r["cpu_s"]["process"], "warm_up_s": r.get("warm_up_s"),
                    "refine_owed_iterations": r.get("refine_owed_iterations"),
                    "map_refine_s": m.get("time_s", {}).get("map_refine")})
    else:
        # offline: every frame read is tracked unless skipped as unusable; none is dropped for time, but the run's
        # own counts say so rather than a constant
        row.update({"tracked_pct": 100 * m["frames_tracked"] / m["frames"], "frames_tracked": m["frames_tracked"],
                    "dropped": m["frames"] - m["frames_tracked"] - len(m.get("skipped_frames", []))})
    return row


def compare(rows: list[dict]) -> None:
    """Add each real-time row's ATE and PSNR against the offline row, and its targets."""
    off = next((r for r in rows if r["mode"] == "offline"), None)
    for r in rows:
        if r["mode"] == "offline" or off is None:
            continue
        r["ate_vs_offline_pct"] = 100 * (r["ate_cm"] / off["ate_cm"] - 1)
        r["psnr_vs_offline_db"] = r["psnr_merged_db"] - off["psnr_merged_db"]
        if r.get("psnr_novel_db") is not None and off.get("psnr_novel_db") is not None:
            r["psnr_novel_vs_offline_db"] = r["psnr_novel_db"] - off["psnr_novel_db"]
        p95 = TARGETS.get(r["rate_hz"])
        if p95 is not None:
            r["targets_met"] = {"latency_p95": r["latency_p95_ms"] <= p95, "ate_within_15pct": r["ate_vs_offline_pct"] <= 15,
                                "psnr_within_1.5db": r["psnr_vs_offline_db"] >= -1.5,
                                **({"tracked_95pct": r["tracked_pct"] >= 95} if r["rate_hz"] == 15.0 else {})}


def run_all(data: Path = REDWOOD, rates=(15.0, 30.0), presets=(None, "realtime"), offline: bool = True) -> dict:
    """The offline run (defaults), then each preset (None: the defaults) at each rate."""
    runs = ([(None, None)] if offline else []) + [(p, r) for p in presets for r in rates]
    rows = []
    for preset, rate in runs:
        print(f"[perf realtime] {'offline' if rate is None else f'{rate:g} Hz'} {preset or 'defaults'} ...",
              file=sys.stderr, flush=True)
        rows.append(measure(data, rate, preset))
        print(json.dumps(rows[-1], default=str), file=sys.stderr, flush=True)
    compare(rows)
    return {"subject": "realtime", "data": str(data), "rows": rows}


COLUMNS = ["mode", "rate_hz", "preset", "tracked_pct", "dropped", "latency_p50_ms", "latency_p95_ms",
           "latency_max_ms", "step_p50_ms", "ate_live_cm", "ate_cm", "ate_vs_offline_pct", "psnr_merged_db",
           "psnr_vs_offline_db", "psnr_novel_db", "psnr_novel_vs_offline_db", "keyframes", "late_views",
           "mapping_iterations_mean", "load_before", "load_after"]
CPU_COLUMNS = ["mode", "rate_hz", "preset", "stream_s", "cpu_tracker_s", "cpu_mapping_s", "cpu_process_s",
               "cores_used", "tracker_cpu_ms_per_frame", "keyframes_deferred", "refinements_skipped",
               "dropped_by_reason", "warm_up_s", "refine_owed_iterations", "map_refine_s"]


def _cpu_row(r: dict) -> dict:
    """A real-time row with what its CPU times say: cores the process used over the stream, and the tracker
    thread's CPU per tracked frame (what a step costs without waiting for a core or the GIL)."""
    return {**r, "cores_used": r["cpu_process_s"] / r["stream_s"],
            "tracker_cpu_ms_per_frame": 1e3 * r["cpu_tracker_s"] / max(1, r["frames_tracked"]),
            "dropped_by_reason": ", ".join(f"{k} {v}" for k, v in r["dropped_by_reason"].items())}


def markdown(res: dict) -> str:
    rows = res["rows"]
    rt = [r for r in rows if r["mode"] != "offline"]
    lines = [f"# Real-time mode on {Path(res['data']).name}", "",
             "`swarmsplat run DATA --realtime --rate HZ` (one agent, Warp on the CPU) against the offline run in the "
             "same process (`python -m perf realtime`). Latency: from the moment a frame is due (its arrival; the "
             "reader decoded and converted it before then, as a camera driver would) to its pose; ATE live: the poses "
             "as emitted; ATE: after the run (loop closures, map refinement); PSNR: the merged map after the run, on "
             "the run's own keyframes (a real-time run has about half the offline run's), and held out: on up to 64 "
             "tracked frames that were neither keyframes nor late views (runtime.late_views: deferred keyframes "
             "the final refinement fits too), which compares the two runs on nearly the same frames. "
             "Load: the machine's 1-minute load average before / after the run (other processes on the same cores "
             "lengthen every latency).", "",
             markdown_table(rows, COLUMNS), "",
             "CPU time over the stream, per thread (their sum above the stream's wall time means tracking and "
             "mapping ran at the same time; the process figure adds the frame reader's decoding). Cores used: the "
             "process's CPU time over the stream's wall time, of the machine's cores; below them, other processes "
             "had the rest. Tracker CPU per frame: the tracker thread's own CPU per tracked frame, a lower bound "
             "of a step's cost (the process figure also holds the reader's decoding and Warp's launch pool, "
             "which runs half of either thread's larger kernels); step_p50_ms above it is waiting for a core "
             "or the GIL. Refinements skipped: frames posed from the coarse stage alone because the frame-to-model "
             "refinement would have passed the latency budget (runtime.skip_late_refinement). Warm-up: the "
             "kernels loaded before the stream (slam.run.realtime.warmup); owed iterations: the mapping "
             "iterations real time cut short, added to the final map refinement (runtime.refine_owed), whose "
             "time after the stream is map_refine_s:", "",
             markdown_table([_cpu_row(r) for r in rt], CPU_COLUMNS), ""]
    for r in rt:
        if r.get("targets_met"):
            met = ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in r["targets_met"].items())
            lines.append(f"- {r['rate_hz']:g} Hz ({r['preset']}): {met}.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf realtime", description=DESCRIPTION)
    p.add_argument("--data", type=Path, default=REDWOOD)
    p.add_argument("--rates", default="15,30", help="comma-separated replay rates (Hz)")
    p.add_argument("--presets", default="defaults,realtime",
                   help="comma-separated config presets (configs/NAME.yaml; 'defaults': none) run at each rate")
    p.add_argument("--no-offline", action="store_true", help="skip the offline run (no comparison)")
    p.add_argument("--json", default=str(RESULTS / "realtime-cpu.json"))
    p.add_argument("--md", default=str(RESULTS / "realtime-cpu.md"))
    p.add_argument("--from-json", action="store_true", help="only write the Markdown again from --json")
    a = p.parse_args(argv)
    if a.from_json:
        res = json.loads(Path(a.json).read_text())
        write_results(None, a.md, res, markdown(res))
        return 0
    if not a.data.is_dir():
        raise SystemExit(f"python -m perf realtime: {a.data} not found (set SWARMSPLAT_SHARED_DATA)")
    machine = machine_info()  # where and from what, as the runs start
    presets = [None if x == "defaults" else x for x in a.presets.split(",")]
    res = {**run_all(a.data, [float(x) for x in a.rates.split(",")], presets, not a.no_offline),
           "machine": machine, "load_after": _load()}
    md = markdown(res)
    print(md)
    write_results(a.json, a.md, res, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
