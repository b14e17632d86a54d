"""What a real-time run measured, as metrics.json's `realtime` block and the Markdown of its report.md: frames
arrived, tracked and dropped (and why), pose latency (arrival -> pose: p50 / p95 / max), mapping iterations per
keyframe, keyframes deferred while mapping was busy, and the CPU time of each thread against the stream's wall
time (their sum above the wall time means they ran at the same time; the process's figure also holds the
reader's decoding and Warp's launch pool, which runs half of either thread's larger kernels)."""

from __future__ import annotations

import collections
import time
from pathlib import Path

import numpy as np

from swarmsplat.kernels.fileio import atomic_write_text

from ..live import latency_ms

DROP_REASONS = {
    "queue_full": "arrived while the tracker was busy and the queue was full: pushed out by a newer frame",
    "stale": "waited so long that its pose would have passed the latency budget, which the next frame's would not",
    "reader_late": "the reader, decoding too slowly, fell a frame behind and skipped it for the one due now",
    "not_arrived": "the run was stopped before the frame arrived",
}


class StreamLog:
    """The tracker thread's record of a stream: each step's duration and each emitted pose with its latency."""

    def __init__(self):
        self.steps: list[float] = []  # s per tracked frame: taken -> pose emitted and keyframe handed over
        self.latency: list[float] = []  # s from a frame's arrival to its pose
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []  # T_world_cam [4, 4] as emitted (the map's frame at that moment)
        self.wall_s = 0.0
        self.cpu_s = 0.0  # CPU time of the whole process over the stream
        self.tracker_cpu_s = 0.0
        self._t = self._c = self._ct = 0.0

    def begin(self) -> None:
        self._t, self._c, self._ct = time.perf_counter(), time.process_time(), time.thread_time()

    def end(self) -> None:
        self.wall_s = time.perf_counter() - self._t
        self.cpu_s = time.process_time() - self._c
        self.tracker_cpu_s = time.thread_time() - self._ct

    def pose(self, timestamp: float, latency_s: float, T_world_cam: np.ndarray) -> None:
        self.stamps.append(float(timestamp))
        self.latency.append(latency_s)
        self.poses.append(np.array(T_world_cam, copy=True))


def realtime_metrics(log: StreamLog, feed, agent, *, n_frames: int, rate_hz: float, rate_from: str,
                     budget_s: float, ate_live: float | None) -> dict:
    """metrics.json's `realtime` block."""
    dropped = collections.Counter(r for _, r in feed.dropped)
    skipped = len(agent.skipped_frames())
    tracked = len(agent.poses)
    accounted = tracked + skipped + sum(dropped.values())
    if accounted < n_frames:
        dropped["not_arrived"] = n_frames - accounted
    its = [r["iterations"] for r in agent.mapping_log]
    planned = [r["planned"] for r in agent.mapping_log]
    return {
        "rate_hz": rate_hz, "rate_from": rate_from, "latency_budget_ms": 1e3 * budget_s, "queue": agent.cfg.runtime.queue,
        "frames": n_frames, "frames_tracked": tracked, "tracked_fraction": tracked / n_frames if n_frames else None,
        "frames_dropped": sum(dropped.values()), "dropped_by_reason": dict(dropped),
        "dropped_frames": {r: [i for i, why in feed.dropped if why == r] for r in dropped if r != "not_arrived"},
        "frames_skipped": skipped,
        "pose_latency_ms": latency_ms(log.latency),
        "step_ms": latency_ms(log.steps),
        "reader_late_ms": latency_ms(feed.late),
        "ate_rmse_live": ate_live,
        "keyframes": len(agent.keyframes), "keyframes_mapped": len(agent.mapping_log),
        "keyframes_deferred": agent.keyframes_deferred,
        "late_views": len(agent.late_views),  # deferred keyframes the final refinement fits (runtime.late_views)
        "refinements_skipped": agent.tracker.refines_skipped,
        "mapping_iterations": {"mean": float(np.mean(its)) if its else None, "min": min(its, default=None),
                               "max": max(its, default=None),
                               "cut_short": sum(1 for a, b in zip(its, planned) if a < b),
                               "per_keyframe": its},
        "mapping_s_per_keyframe": float(np.mean([r["mapping_s"] for r in agent.mapping_log])) if its else None,
        "loop_closure_s_per_keyframe": (float(np.mean([r["loop_closure_s"] for r in agent.mapping_log]))
                                        if its else None),
        "stream_s": log.wall_s,
        "cpu_s": {"process": log.cpu_s, "tracker_thread": log.tracker_cpu_s, "mapping_thread": agent.worker_cpu_s},
    }


def _ms(x) -> str:
    return "–" if x is None else f"{x:.1f}"


def report_markdown(m: dict) -> str:
    """report.md of a real-time run from its metrics.json."""
    r = m["realtime"]
    lat, step = r["pose_latency_ms"], r["step_ms"]
    cpu = r["cpu_s"]
    its = r["mapping_iterations"]
    L = [f"# swarmsplat real-time run: {Path(m.get('dataset', '')).name}", "",
         f"{r['frames']} frames replayed at {r['rate_hz']:.2f} Hz ({r['rate_from']}) over {r['stream_s']:.1f} s: "
         f"**{r['frames_tracked']} tracked ({100 * (r['tracked_fraction'] or 0):.1f} %)**, {r['frames_dropped']} "
         f"dropped, {r['frames_skipped']} skipped (unusable input).", "",
         "## Pose latency (frame due, already decoded and converted, to pose)", "",
         "| | p50 | p95 | max |", "|---|---:|---:|---:|",
         f"| latency [ms] | {_ms(lat['p50'])} | {_ms(lat['p95'])} | {_ms(lat['max'])} |",
         f"| tracker step [ms] | {_ms(step['p50'])} | {_ms(step['p95'])} | {_ms(step['max'])} |", "",
         f"Latency budget {r['latency_budget_ms']:.1f} ms, queue of {r['queue']} frame(s); "
         f"{r.get('refinements_skipped', 0)} frames posed without the frame-to-model refinement, which would have "
         "passed the budget.", ""]
    if r["frames_dropped"]:
        L += ["## Dropped frames", "", "| reason | frames | what happened |", "|---|---:|---|"]
        L += [f"| {k} | {v} | {DROP_REASONS.get(k, k)} |" for k, v in r["dropped_by_reason"].items()]
        L.append("")
    L += ["## Mapping beside tracking", "",
          f"{r['keyframes']} keyframes ({r['keyframes_deferred']} frames were due to be keyframes while mapping was "
          f"still busy and waited for the next one; {r.get('late_views', 0)} of them kept as late views, which "
          f"the final map refinement fits as keyframes); mapping iterations per keyframe: mean "
          f"{_ms(its['mean'])}, min {its['min']}, max {its['max']}, {its['cut_short']} keyframes cut short by the "
          f"next one. Per keyframe: mapping {_ms(1e3 * (r['mapping_s_per_keyframe'] or 0))} ms, loop closure "
          f"{_ms(1e3 * (r['loop_closure_s_per_keyframe'] or 0))} ms.", "",
          f"CPU time over the stream: tracker thread {cpu['tracker_thread']:.1f} s, mapping thread "
          f"{cpu['mapping_thread']:.1f} s, whole process {cpu['process']:.1f} s in {r['stream_s']:.1f} s of wall "
          "time.", "",
          "## Accuracy", "", "| | value |", "|---|---:|"]
    for key, name, scale, unit in (("ate_rmse_live", "ATE of the poses as emitted", 100, "cm"),
                                   ("ate_rmse", "ATE after the run (loop closures, refinement)", 100, "cm"),
                                   ("psnr_merged", "merged map PSNR", 1, "dB")):
        v = r.get(key) if key in r else m.get(key)
        L.append(f"| {name} | {'–' if v is None else f'{scale * v:.2f} {unit}'} |")
    return "\n".join(L + [""])


def write_report(out: Path, metrics: dict) -> Path:
    path = Path(out) / "report.md"
    atomic_write_text(path, report_markdown(metrics))
    return path
