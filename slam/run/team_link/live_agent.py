"""A team agent on live ROS 2 topics (`swarmsplat agent zenoh/[PREFIX] --server ENDPOINT --id K`): the robot's
camera frames arrive over Zenoh (slam.io.live.ZenohRos2Source), the agent tracks and maps each as it comes,
publishes what a lone live agent does (pose, TF, path, map, loops: slam.run.ros2.feed), its path again whenever the
server's corrections move its map, and sends the server its keyframes,
submaps and poses as a recorded team member does (slam.run.team_link.agent_node). It joins without a frame count,
so the server never waits for it (slam.run.team_link.server_node); the stream ends on --frames, on
--idle-timeout seconds without a sample, or on Ctrl-C, and the agent then waits for the server to acknowledge
everything it sent. With --out it keeps checkpoints and logs the frames read since the last one
(slam.run.checkpoint.frame_log); --resume tracks those again, then goes on live.
"""

from __future__ import annotations

import sys
import time

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.team.held import held_bytes


def run_live_team_agent(source, index: int, config: SlamConfig | None = None, *, name: str | None = None,
                        connect: list[str] | None = None, listen: list[str] | None = None, run: str = "team",
                        publisher=None, max_frames: int = 0, idle_timeout: float = 0.0, camera_timeout: float = 30.0,
                        silent_warning: float = 5.0, map_period: float = 10.0, progress: bool = True,
                        out=None, resume: bool = False) -> dict:
    """Agent `index` of a team on the live `source`, sending to the server at `connect`; what it publishes (pose,
    TF, path, submaps, map every `map_period` s, loops) goes to `publisher` (slam.io.ros2.AgentTopics) in the agent's
    world frame as the server last corrected it, the path again after each correction. With `out`, it keeps its
    pose journal, checkpoints (config checkpoint.every_submaps) and the frames read since the last one
    (slam.run.checkpoint.frame_log) there; `resume` continues the agent killed in `out`: the logged frames again,
    then the frames that arrive now. Returns the agent's link figures, plus `frames_tracked`, `reason` (why the
    stream ended), `poses_published` and `frames_replayed`."""
    from dataclasses import replace

    from swarmsplat.kernels.fileio import output_dir
    from swarmsplat.slam.run.live import _Stop, end_reason, live_identity, logged_then_live
    from swarmsplat.slam.run.runtime import check_device, use_kernels
    from swarmsplat.slam.run.ros2.feed import AgentFeed

    from . import messages as L
    from .agent_node import AgentNode
    from swarmsplat.slam.run.checkpoint.frame_log import FrameLog
    from .member import MemberCheckpoints
    from .processes import _transport, check_member, finish_agent

    cfg = config or SlamConfig()
    connect = check_member(index, connect, listen)
    if resume and out is None:
        raise InputError("--resume continues the team agent whose checkpoint is in --out: give --out")
    use_kernels(cfg.kernels)
    name = name or source.name
    say = (lambda *a, **k: print(*a, **k)) if progress else (lambda *a, **k: None)
    camera = source.wait_camera(camera_timeout)
    check_device(cfg.kernels, [camera], cfg.image.max_width)
    ckpt = MemberCheckpoints(output_dir(out, "--out"), {**live_identity(name, camera, cfg), "team_index": int(index)},
                             cfg) if out is not None else None
    try:
        resumed = ckpt.open(resume) if ckpt is not None else None  # a bad folder stops the agent before it connects
        log = FrameLog(out) if ckpt is not None and cfg.checkpoint.every_submaps else None
        tx = _transport(index + 1, [L.SERVER, index + 1], listen=list(listen or []), connect=connect, run=run)
        try:
            make = lambda: AgentNode(camera, cfg, name, tx)  # noqa: E731
            node, i = ckpt.start(resumed, make, tx, say=lambda t: say(t, file=sys.stderr)) if ckpt else (make(), 0)
            if log is not None:
                log.trim(i) if resume else log.clear()
            node.join(0, cfg.link.connect_timeout_s, say=say)  # 0 rounds: a live stream's length is not known
            feed = AgentFeed(publisher, map_period_s=map_period) if publisher is not None else None
            reason, last, t_last, replayed, n_live = "source ended", time.monotonic(), 0.0, 0, 0
            with _Stop() as stop:
                live = source.frames(max_frames=max_frames, idle_timeout=idle_timeout,
                                     silent_warning=silent_warning, stop=lambda: stop.requested)
                again = log.replay(i) if log is not None and resume else ()
                for frame, arrival, _taken in logged_then_live(again, live):
                    if stop.requested:
                        break
                    is_live = arrival is not None
                    if is_live:  # numbered on from the last frame read, this process life or an earlier one
                        frame = replace(frame, index=i)
                    i = frame.index
                    if log is not None and is_live:
                        log.append(frame)  # before tracking: a kill from here on finds it again
                    n_sm = len(node.agent.gmap.submaps)
                    rec = node.step_frame(frame, i)
                    if ckpt is not None and ckpt.after_round(node, i, n_sm) and log is not None:
                        log.trim(i + 1)
                    i += 1
                    t_last = frame.timestamp
                    replayed += not is_live
                    n_live += is_live
                    if feed is not None and is_live:  # the server's corrections move the map: the path follows
                        feed.step(node.agent, frame.timestamp, rec, moved=node.corrections)
                    if progress and time.monotonic() - last > 10:
                        last = time.monotonic()
                        say(f"[{name}] frame {i}  keyframes {len(node.agent.keyframes)}  queued "
                            f"{len(node.outbox.items)}  held {held_bytes(node.agent, node.outbox) / 2**20:.0f} MB",
                            file=sys.stderr)
                reason = end_reason(stop.requested, max_frames, n_live, idle_timeout) or reason
            if ckpt is not None:  # every frame read: a kill while waiting for the server resumes here
                ckpt.save(node, i)
                if log is not None:
                    log.trim(i)
            figures = finish_agent(node, i, tx, name, out, say)
            if feed is not None:  # after the server's last corrections
                feed.finish(node.agent, t_last)
            if ckpt is not None and figures["acknowledged"]:
                ckpt.done()
                if log is not None:
                    log.clear()
        finally:
            tx.close()
    finally:
        if ckpt is not None:
            ckpt.close()
    return {**figures, "frames_tracked": len(node.agent.poses), "reason": reason,
            "poses_published": getattr(publisher, "published", 0), "frames_replayed": replayed}

