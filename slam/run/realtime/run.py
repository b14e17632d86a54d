"""`swarmsplat run DATASET --realtime [--rate HZ]`: one agent on a sequence replayed at the sensor's rate.

Frames arrive at their timestamps or at `runtime.rate` (feed.FrameFeed); the calling thread tracks each one it can
take in time and emits its pose (arrival -> pose latency measured per frame); mapping and loop closure run on the
agent's worker thread on keyframes (agent.RealtimeAgent). A frame the tracker cannot take in time is dropped and
counted: pushed out of the full queue by a newer one, or "stale" (schedule.Scheduler: its wait plus the expected
time to its pose would pass the latency budget, runtime.max_latency_ms, while a fresh frame's would not). A pose
goes out as soon as tracking has it; a keyframe's hand-over to the worker comes after it. After the
stream the worker finishes its keyframe and the run ends as an offline run does (map refinement, evaluation,
results; slam.run.sequence.finish_agent_run), with metrics.json `realtime` and report.md (summary). Ctrl-C stops
the replay and the worker and keeps every pose tracked so far (slam.run.guard).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from swarmsplat.kernels.fileio import atomic_write_text, output_dir
from swarmsplat.slam.config import SlamConfig

from ..guard import guarded, keep
from ..partial_results import write_partial_agent
from .agent import RealtimeAgent
from .feed import FrameFeed, arrival_offsets
from .schedule import Scheduler
from .warmup import warm_up
from .summary import StreamLog, realtime_metrics, write_report


@guarded("run")
def run_realtime(dataset_path: str | Path, out_dir: str | Path, config: SlamConfig | None = None, *,
                 frames: int | None = None, progress: bool = True, strict: bool = False, on_pose=None) -> dict:
    """Replay `dataset_path` (a path any loader reads, or a loaded sequence) in real time with one agent; returns
    the metrics written to out_dir/metrics.json (those of an offline run plus `realtime`). on_pose, if given, is
    called on the tracking thread with each pose as it is emitted: on_pose(frame index, timestamp (s),
    T_world_cam [4, 4], latency (s) from the frame's arrival); its time counts in the next frame's wait."""
    from swarmsplat.slam.io.progress import bar

    from ..checkpoint import PoseJournal
    from ..runtime import check_device, use_kernels
    from ..sequence import JOURNAL, _trajectory_metrics, finish_agent_run, offload, open_sequence, refines

    cfg = config or SlamConfig()
    rt = cfg.runtime
    use_kernels(cfg.kernels)
    seq, n = open_sequence(dataset_path, cfg, frames)
    offsets, interval = arrival_offsets(seq.timestamps, n, rt.rate)
    rate = 1.0 / interval if interval > 0 else 0.0
    budget = rt.max_latency_ms / 1e3 if rt.max_latency_ms else interval
    check_device(cfg.kernels, [seq.camera], cfg.image.max_width)
    out = output_dir(out_dir, "--out")
    atomic_write_text(out / "config.yaml", cfg.to_yaml())

    def read(i):
        f = seq[i]
        return f.color, f.depth

    warm_s = warm_up(seq.camera, cfg, read, n)  # every kernel loaded before the clock starts
    agent = RealtimeAgent(seq.camera, cfg, name=seq.name)
    offload(agent, out, cfg)  # finished submaps and their keyframes' images to the run folder (config submaps)
    agent.keep_keyframe_images = refines(cfg) and cfg.map_refine.views == "mapping"
    feed = FrameFeed(seq, offsets, queue=rt.queue, skipper=agent, strict=strict, prepare=agent.prepare)
    journal = PoseJournal(out / JOURNAL)
    log = StreamLog()
    sched = Scheduler(budget)
    t0 = time.perf_counter()

    def save(status: str, reason: str):
        feed.stop()
        agent.stop(1.0)
        return write_partial_agent(agent, out, status=status, reason=reason, n_frames=n,
                                   wall_s=time.perf_counter() - t0)

    keep(save)
    if progress:
        print(f"[{seq.name}] real time: {n} frames at {rate:.2f} Hz, latency budget {1e3 * budget:.0f} ms",
              file=sys.stderr)
    try:
        with journal, bar(n, f"[{seq.name}] frames", unit="frame", enabled=progress) as b:
            feed.start()
            log.begin()
            seen = 0
            while (a := feed.take()) is not None:
                now = time.monotonic()
                if (why := sched.take(now, a.due)) is not None:
                    feed.drop(a, why)
                else:
                    f = a.frame
                    rec = agent.track(f.index, f.timestamp, None, None, prepared=a.prepared, deadline=a.due + budget)
                    posed = time.monotonic()
                    if rec is not None:
                        sched.posed(now, posed)
                        T = agent.gmap.submaps[rec.submap_id].T_world_local @ rec.T_local_cam
                        log.pose(f.timestamp, posed - a.due, T)
                        if on_pose is not None:
                            on_pose(f.index, f.timestamp, T, posed - a.due)
                    agent.hand_over_keyframe()  # after the pose went out: its cost falls in the idle time
                    log.steps.append(time.monotonic() - now)
                    journal.follow(agent)
                accounted = len(agent.poses) + len(agent.time.skipped) + len(feed.dropped)
                b.update(accounted - seen, f"{len(agent.gmap)} Gaussians  {len(feed.dropped)} dropped")
                seen = accounted
                sched.free(time.monotonic())
            log.end()
            agent.finish()  # the keyframe being mapped, then the worker stops
            agent.end_stream()
    finally:
        feed.stop()
        agent.stop(1.0)
    ate_live = None
    if log.poses:
        ate_live = _trajectory_metrics(seq, np.array(log.stamps), np.stack(log.poses), None)["ate_rmse"]
    extra = {"realtime": realtime_metrics(log, feed, agent, n_frames=n, rate_hz=rate,
                                          rate_from="--rate" if rt.rate else "timestamps", budget_s=budget,
                                          ate_live=ate_live)}
    owed = owed_iterations(agent.mapping_log, len(agent.late_views), cfg.mapping.iterations) if rt.refine_owed else 0
    extra["realtime"].update({"warm_up_s": warm_s, "refine_owed_iterations": owed})
    views = len(agent.keyframes) + len(agent.late_views)  # what the refinement fits: slam.dense.mapping.refine
    metrics = finish_agent_run(agent, seq, out, with_owed_iterations(cfg, views, owed), n_frames=n,
                               t0=t0, progress=progress, extra=extra)
    write_report(out, metrics)
    return metrics


def owed_iterations(mapping_log: list[dict], late_views: int = 0, iterations: int = 0) -> int:
    """The mapping iterations real time cut short: each mapped keyframe's planned (what the offline run gives it)
    less what it got, and `iterations` (mapping.iterations) for each of the `late_views`, which an offline run
    would have mapped as keyframes."""
    return int(sum(max(0, r["planned"] - r["iterations"]) for r in mapping_log)) + late_views * iterations


def with_owed_iterations(cfg: SlamConfig, keyframes: int, owed: int) -> SlamConfig:
    """`cfg` whose map refinement (slam.dense.mapping.refine_merged.iteration_budget) runs `owed` steps more than
    its own budget for `keyframes` views (keyframes and late views): runtime.refine_owed. After the stream nothing waits for the map, so
    what mapping could not do in time is done there, on the merged map, one keyframe view per step as a mapping
    iteration is. Unchanged when owed is 0 or the refinement is off."""
    rc = cfg.map_refine
    if owed <= 0 or keyframes <= 0 or rc.iterations_per_keyframe <= 0 or rc.max_iterations <= 0:
        return cfg
    total = min(rc.max_iterations, rc.iterations_per_keyframe * keyframes) + owed
    return cfg.override({"map_refine": {"iterations_per_keyframe": -(-total // keyframes), "max_iterations": total}})


def summary(metrics: dict) -> dict:
    """The few real-time figures `swarmsplat run --realtime` prints: tracked share, drops, latency, live ATE."""
    r = metrics["realtime"]
    return {k: r[k] for k in ("rate_hz", "frames_tracked", "tracked_fraction", "frames_dropped", "dropped_by_reason",
                              "pose_latency_ms", "ate_rmse_live")}
