"""One agent on a live robot: RGB-D frames from ROS 2 topics over Zenoh (slam.io.live), each frame's pose published
back as it is tracked, the run's results written when it ends — what `swarmsplat agent --source zenoh/...` runs.

The run ends at `max_frames`, after `idle_timeout` seconds without a sample, or on Ctrl-C / SIGTERM (the normal
end of a live run: status "complete", reason "stopped"); a second interrupt ends it at once. As it goes it appends
progress/poses.tum (the pose journal, fsync'd at each keyframe: a hard kill keeps every pose up to the last
keyframe). At the end it writes trajectory.txt / trajectory_no_lc.txt / keyframes.txt (TUM), map.ply, loops.csv,
config.yaml and metrics.json with the publishing time per frame (publish_ms: what the caller's thread spends on
ROS 2 output), the pose latency (arrival of the frame's later message -> pose published: p50 /
p95 / max; it includes the time a frame waits while the agent works on earlier ones), the overhead (decoding and
publishing: the latency less the queue wait and the agent's step) and what the source saw (samples per topic,
frames, unpaired, dropped). There is no ground truth live: `swarmsplat eval` scores trajectory.txt later.
"""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

import numpy as np

from swarmsplat.kernels.fileio import atomic_write_text, output_dir
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.agent import Agent

from .checkpoint import PoseJournal
from .guard import guarded, keep
from .partial_results import agent_counts, write_partial_agent
from .ros2.feed import AgentFeed
from .runtime import kernels_record


def latency_ms(values: list[float]) -> dict:
    """{"p50", "p95", "max" (ms), "count"} of latencies given in seconds (None each when there are none)."""
    if not values:
        return {"p50": None, "p95": None, "max": None, "count": 0}
    v = np.asarray(values) * 1e3
    return {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95)), "max": float(v.max()),
            "count": len(v)}


class _Stop:
    """Ctrl-C / SIGTERM end the frame loop (a live run's normal end); a second one raises as usual."""

    def __init__(self):
        self.requested = False
        self._old = {}

    def __enter__(self):
        def handler(signum, frame):
            if self.requested:
                raise KeyboardInterrupt(f"signal {signum}")
            self.requested = True

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[sig] = signal.signal(sig, handler)
            except ValueError:  # not the main thread: the caller stops the source instead
                pass
        return self

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)


@guarded("agent")
def run_live(source, out_dir: str | Path, config: SlamConfig | None = None, *, publisher=None,
             max_frames: int = 0, idle_timeout: float = 0.0, camera_timeout: float = 30.0,
             silent_warning: float = 5.0, map_period: float = 10.0, progress: bool = True,
             resume: bool = False) -> dict:
    """Track and map the frames of a live `source` (slam.io.live.ZenohRos2Source) until it ends; publish its pose,
    TF, path, submaps, map (every `map_period` s; 0: at the end only) and loops on `publisher` (slam.io.ros2.
    AgentTopics, or slam.io.live.PosePublisher for plain keys) if given. Checkpoints as `swarmsplat run` writes
    them (config checkpoint.every_submaps) and logs the frames read since the last one (slam.run.checkpoint.
    frame_log); `resume`: continue the agent killed in `out_dir` from its last one, on the logged frames and then
    the frames that arrive now. Returns the metrics written to out_dir/metrics.json."""
    from dataclasses import replace

    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.io.jsonio import write_json
    from swarmsplat.slam.io.progress import bar
    from swarmsplat.slam.io.trajectory import write_tum

    from .checkpoint import CHECKPOINT, find_resume, save_checkpoint
    from .checkpoint.frame_log import FrameLog
    from .runtime import check_device, use_kernels
    from .sequence import JOURNAL, _write_loops_csv

    cfg = config or SlamConfig()
    use_kernels(cfg.kernels)
    out = output_dir(out_dir, "--out")
    camera = source.wait_camera(camera_timeout)
    check_device(cfg.kernels, [camera], cfg.image.max_width)  # a device that computes wrongly stops here
    identity = live_identity(source.name, camera, cfg)
    resumed = find_resume(out, identity) if resume else None
    atomic_write_text(out / "config.yaml", cfg.to_yaml())
    agent = resumed.agent if resumed else Agent(camera, cfg, name=source.name)
    first = resumed.next_frame if resumed else 0  # the index of the first frame read now
    log = FrameLog(out) if cfg.checkpoint.every_submaps else None
    if log is not None:
        log.trim(first) if resume else log.clear()
    if resume and progress:
        print(f"[{source.name}] resuming after {first} frames" if resumed else
              f"[{source.name}] no checkpoint in {out} yet: starting anew", file=sys.stderr)
    # a hard kill keeps every pose up to the last keyframe
    journal = PoseJournal(out / JOURNAL, resume=resumed.journal if resumed else None)
    frames: list[tuple] = []  # per published pose: (arrival, taken from the queue, agent's step s, handed over)
    t0 = time.perf_counter() - (resumed.wall_s if resumed else 0.0)
    every, n_read = cfg.checkpoint.every_submaps, first
    keep(lambda status, reason: write_partial_agent(agent, out, status=status, reason=reason,
                                                    n_frames=len(agent.poses), wall_s=time.perf_counter() - t0))
    feed = AgentFeed(publisher, map_period_s=map_period) if publisher is not None else None
    t_last = 0.0
    reason = "source ended"
    replayed = n_live = 0
    with _Stop() as stop, journal, bar(max_frames or None, f"[{source.name}] live frames", unit="frame",
                              enabled=progress) as b:
        live = source.frames(max_frames=max_frames, idle_timeout=idle_timeout, silent_warning=silent_warning,
                             stop=lambda: stop.requested)
        again = log.replay(first) if log is not None and resume else ()
        for frame, arrival, taken in logged_then_live(again, live):
            is_live = arrival is not None
            if is_live:  # numbered on from the last frame read, this process life or an earlier one
                frame = replace(frame, index=n_read)
                if log is not None:
                    log.append(frame)  # before tracking: a kill from here on finds it again
            t_step = time.monotonic()
            n_submaps = len(agent.gmap.submaps)
            rec = agent.step(frame.index, frame.timestamp, frame.color, frame.depth)
            step = time.monotonic() - t_step
            journal.follow(agent)
            n_read = frame.index + 1
            replayed += not is_live
            n_live += is_live
            finished = len(agent.gmap.submaps) - 1
            if every and len(agent.gmap.submaps) > n_submaps and finished and finished % every == 0:
                save_checkpoint(out, identity, agent, next_frame=n_read, journal=journal.state(),
                                wall_s=time.perf_counter() - t0)
                if log is not None:
                    log.trim(n_read)
            if feed is not None and is_live:  # the logged frames' poses went out before the kill
                feed.step(agent, frame.timestamp, rec)
                if rec is not None:
                    frames.append((arrival, taken, step, time.monotonic()))
            t_last = frame.timestamp
            b.update(1, f"{len(agent.gmap)} Gaussians")
        reason = end_reason(stop.requested, max_frames, n_live, idle_timeout) or reason
    if feed is not None:
        feed.finish(agent, t_last)  # the last path, submaps, loops and the whole map
    # a pose is published when its thread sent it (in order); without that record, when it was handed over
    sent = getattr(publisher, "pose_sent_at", None)
    done = sent if sent is not None and len(sent) == len(frames) else [f[3] for f in frames]
    latency = [d - f[0] for f, d in zip(frames, done)]
    overhead = [d - f[1] - f[2] for f, d in zip(frames, done)]  # decoding and publishing, beyond the agent
    wall = time.perf_counter() - t0
    stamps, T_est = agent.trajectory(per_keyframe=True)
    if len(stamps):
        write_tum(out / "trajectory.txt", stamps, T_est)
        write_tum(out / "trajectory_no_lc.txt", stamps, agent.trajectory_no_lc()[1])
    if agent.keyframes:
        write_tum(out / "keyframes.txt", np.array([k.timestamp for k in agent.keyframes]), agent.keyframe_world_poses())
    if agent.gmap.submaps:
        save_ply(out / "map.ply", agent.display_map(), max_color=None)
    _write_loops_csv(out / "loops.csv", agent.loops.log_rows())
    st = source.stats
    t = agent.time
    metrics = {
        "status": "complete", "reason": reason, "agent": agent.name, "source": getattr(source, "describe", lambda: "")(),
        **agent_counts(agent),
        "loop_candidates": len(agent.loops.log), "loops_accepted": sum(1 for c in agent.loops.log if c.accepted),
        "pose_graph_optimisations": agent.loops.optimisations,
        "pose_latency_ms": latency_ms(latency), "pose_overhead_ms": latency_ms(overhead),
        "poses_published": getattr(publisher, "published", 0), "frames_replayed": replayed,
        "publish_ms": latency_ms(feed.publish_s) if feed is not None else latency_ms([]),
        "ros2": publisher.stats() if hasattr(publisher, "stats") else None,
        "live": {"samples": dict(st.samples), "frames": st.frames, "unpaired": st.unpaired, "dropped": st.dropped,
                 "undecodable": st.undecodable},
        "fps": len(agent.poses) / wall if wall > 0 else float("nan"),
        "time_s": {"total": wall, "tracking": t.tracking, "mapping": t.mapping, "loop_closure": t.loop_closure},
        "kernels": kernels_record(cfg.kernels),
    }
    write_json(out / "metrics.json", metrics)
    (out / CHECKPOINT).unlink(missing_ok=True)  # a complete run needs none; the journal stays
    if log is not None:
        log.clear()
    return metrics


def end_reason(stopped: bool, max_frames: int, n_live: int, idle_timeout: float) -> str | None:
    """Why a live stream ended: "stopped" (Ctrl-C), "max_frames", "no sample for S s"; None when the source
    itself ended."""
    if stopped:
        return "stopped"
    if max_frames and n_live >= max_frames:
        return "max_frames"
    if idle_timeout:
        return f"no sample for {idle_timeout:g} s"
    return None


def logged_then_live(again, live):
    """(frame, arrival, taken): the logged frames first (arrival and taken None), then the live source's."""
    for f in again:
        yield f, None, None
    yield from live


def live_identity(name: str, camera, cfg: SlamConfig) -> dict:
    """What a live agent's checkpoint must share with the agent that resumes it: its name, camera and config (all
    but the `checkpoint` section)."""
    config = cfg.model_dump(mode="json")
    config.pop("checkpoint", None)
    return {"live_agent": name, "camera": {k: float(v) for k, v in camera.to_dict().items()}, "config": config}
