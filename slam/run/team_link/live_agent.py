"""A team agent on live ROS 2 topics (`swarmsplat agent zenoh/[PREFIX] --server ENDPOINT --id K`): the robot's
camera frames arrive over Zenoh (slam.io.live.ZenohRos2Source), the agent tracks and maps each as it comes,
publishes what a lone live agent does (pose, TF, path, map, loops: slam.run.ros2.feed), its path again whenever the
server's corrections move its map, and sends the server its keyframes,
submaps and poses as a recorded team member does (slam.run.team_link.agent_node). It joins without a frame count,
so the server never waits for it (slam.run.team_link.server_node); the stream ends on --frames, on
--idle-timeout seconds without a sample, or on Ctrl-C, and the agent then waits for the server to acknowledge
everything it sent.
"""

from __future__ import annotations

import sys
import time

from swarmsplat.slam.config import SlamConfig


def run_live_team_agent(source, index: int, config: SlamConfig | None = None, *, name: str | None = None,
                        connect: list[str] | None = None, listen: list[str] | None = None, run: str = "team",
                        publisher=None, max_frames: int = 0, idle_timeout: float = 0.0, camera_timeout: float = 30.0,
                        silent_warning: float = 5.0, map_period: float = 10.0, progress: bool = True,
                        out=None) -> dict:
    """Agent `index` of a team on the live `source`, sending to the server at `connect`; what it publishes (pose, TF,
    path, submaps, map every `map_period` s, loops) goes to `publisher` (slam.io.ros2.AgentTopics) in the agent's
    world frame as the server last corrected it, the path again after each correction. Returns
    the agent's link figures, plus `frames_tracked`, `reason` (why the stream ended) and `poses_published`."""
    from swarmsplat.slam.run.live import _Stop
    from swarmsplat.slam.run.runtime import check_device, use_kernels
    from swarmsplat.slam.run.ros2.feed import AgentFeed

    from . import messages as L
    from .agent_node import AgentNode
    from .processes import _transport, agent_journal, check_member, finish_agent

    cfg = config or SlamConfig()
    connect = check_member(index, connect, listen)
    use_kernels(cfg.kernels)
    name = name or source.name
    say = (lambda *a, **k: print(*a, **k)) if progress else (lambda *a, **k: None)
    camera = source.wait_camera(camera_timeout)
    check_device(cfg.kernels, [camera], cfg.image.max_width)
    tx = _transport(index + 1, [L.SERVER, index + 1], listen=list(listen or []), connect=connect, run=run)
    try:
        node = AgentNode(camera, cfg, name, tx)
        node.journal = agent_journal(out)
        node.join(0, cfg.link.connect_timeout_s, say=say)  # 0 rounds: a live stream's length is not known
        feed = AgentFeed(publisher, map_period_s=map_period) if publisher is not None else None
        i, reason, last, t_last = 0, "source ended", time.monotonic(), 0.0
        with _Stop() as stop:
            for frame, _arrival, _taken in source.frames(max_frames=max_frames, idle_timeout=idle_timeout,
                                                         silent_warning=silent_warning,
                                                         stop=lambda: stop.requested):
                rec = node.step_frame(frame, i)
                i += 1
                t_last = frame.timestamp
                if feed is not None:  # the server's corrections move the map: the path follows
                    feed.step(node.agent, frame.timestamp, rec, moved=node.corrections)
                if progress and time.monotonic() - last > 10:
                    last = time.monotonic()
                    say(f"[{name}] frame {i}  keyframes {len(node.agent.keyframes)}  queued "
                        f"{len(node.outbox.items)}", file=sys.stderr)
            if stop.requested:
                reason = "stopped"
            elif max_frames and i >= max_frames:
                reason = "max_frames"
            elif idle_timeout:
                reason = f"no sample for {idle_timeout:g} s"
        figures = finish_agent(node, i, tx, name, out, say)
        if feed is not None:  # after the server's last corrections
            feed.finish(node.agent, t_last)
    finally:
        tx.close()
    return {**figures, "frames_tracked": len(node.agent.poses), "reason": reason,
            "poses_published": getattr(publisher, "published", 0)}
