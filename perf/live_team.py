"""A live robot in a team against the same frames from a recording in the team: is the live agent's corrected
trajectory on the server as good?

Redwood living room 1 (211 frames, 640x480; a generated 60-frame sequence without ../shared/data) cut in two as the
README's example cuts it (`--split 0:110,100:`; --quick: the generated sequence, `0:34,26:`), the default config:
  recorded  `swarmsplat run DATA --split S --processes`: both agents from the recording, each in its own process;
  live      `swarmsplat server --agents 2 --dataset DATA --split S` and `swarmsplat agent DATA --split S --id 0
            --server ...` in their own processes; agent 1 in this process on live ROS 2 topics over Zenoh
            (slam.run.team_link.live_agent), its frames played by a camera driver at 15 Hz as colour bgr8, depth
            16UC1 and CameraInfo, the way the Zenoh-ROS 2 bridge forwards them.
The figure is each agent's ATE on the server (metrics.json of the team) and the live agent's against the recorded
one's (the issue's bound: within 10 %). The live team's order of keyframes at the server depends on timing, so one
run is one sample.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

DESCRIPTION = "a live agent in a team: its ATE on the server against the same frames from a recording in the team"
REDWOOD = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) \
    / "redwood_livingroom1_211"


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "swarmsplat.slam", *args]


def _ates(out: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    return {a["name"]: a.get("ate_rmse") for a in m["agents"]}, m


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import zenoh

    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence
    from swarmsplat.slam.io.live import ZenohRos2Source, zenoh_config
    from swarmsplat.slam.io.ros2 import AgentTopics, Ros2Node
    from swarmsplat.slam.run.team_link.live_agent import run_live_team_agent

    from .live import _drive, _messages, _port

    scratch = Path(tempfile.mkdtemp(prefix="perf-live-team-"))
    if REDWOOD.is_dir() and not quick:
        data, split, name = REDWOOD, "0:110,100:", "redwood_livingroom1_211"
    else:
        from swarmsplat.slam.synthetic import GeneratorConfig, generate

        data = generate(scratch / "data", GeneratorConfig.preset("default", agents=1, frames=60)) / "agent_0"
        split, name = "0:34,26:", "generated"
    cfg = SlamConfig().override({"kernels": {"backend": backends[0], "device": device}})
    cfg_path = scratch / "config.yaml"
    cfg_path.write_text(cfg.to_yaml())
    seqs = split_sequence(load_dataset(data).agents[0], parse_ranges(split)).agents
    base = ["--config", str(cfg_path), "--quiet"]

    t0 = time.perf_counter()
    subprocess.run(_cli("run", str(data), "--split", split, "--processes", "--out", str(scratch / "recorded"),
                        *base), check=True, stdout=subprocess.DEVNULL)
    recorded_s = time.perf_counter() - t0
    rec_ate, _ = _ates(scratch / "recorded")

    port = _port()
    server_at = f"tcp/127.0.0.1:{port}"
    t0 = time.perf_counter()
    server = subprocess.Popen(_cli("server", "--agents", "2", "--out", str(scratch / "live"), "--dataset", str(data),
                                   "--split", split, "--listen", server_at, *base), stdout=subprocess.DEVNULL)
    agent0 = subprocess.Popen(_cli("agent", str(data), "--split", split, "--id", "0", "--server", server_at, *base),
                              stdout=subprocess.DEVNULL)
    cam = _port()
    src = ZenohRos2Source("", name=seqs[1].name, listen=[f"tcp/127.0.0.1:{cam}"])
    _, conf = zenoh_config(connect=[f"tcp/127.0.0.1:{cam}"])
    driver = zenoh.open(conf)
    node = Ros2Node(src.session, "swarmsplat_" + seqs[1].name)
    topics = AgentTopics(node, seqs[1].name)
    try:
        t_end = time.time() + 20
        while time.time() < t_end and not (list(src.session.info.peers_zid()) and list(driver.info.peers_zid())):
            time.sleep(0.05)
        time.sleep(0.5)
        started = threading.Event()
        th = threading.Thread(target=_drive, args=(driver, _messages(seqs[1], len(seqs[1])), 15.0, started),
                              daemon=True)
        th.start()
        started.set()
        m = run_live_team_agent(src, 1, cfg, name=seqs[1].name, connect=[server_at], publisher=topics,
                                max_frames=len(seqs[1]), camera_timeout=60, idle_timeout=60, progress=False)
        th.join()
        for p in (agent0, server):
            p.wait(timeout=1800)
    finally:
        topics.close()
        node.close()
        driver.close()
        src.close()
        for p in (agent0, server):
            if p.poll() is None:
                p.kill()
    live_s = time.perf_counter() - t0
    live_ate, team = _ates(scratch / "live")
    live_name = seqs[1].name
    rows = []
    for k, s in enumerate(seqs):
        rows.append({"agent": s.name, "frames": len(s), "input": "live ROS 2 topics" if k == 1 else "recording",
                     "ate_cm_recorded_team": round(100 * rec_ate[s.name], 3) if rec_ate.get(s.name) else None,
                     "ate_cm_live_team": round(100 * live_ate[s.name], 3) if live_ate.get(s.name) else None})
    ratio = live_ate[live_name] / rec_ate[live_name] if live_ate.get(live_name) and rec_ate.get(live_name) else None
    return {"rows": rows, "columns": list(rows[0]),
            "notes": [f"frames: {name} split {split}; default config; kernels {backends[0]} on {device}",
                      f"the live agent's ATE on the server over the recorded team's: "
                      f"{ratio:.3f}" if ratio else "the live agent's ATE is missing",
                      f"live agent: {m['frames_tracked']} frames tracked ({m['reason']}), {m['poses_published']} poses "
                      f"published, all acknowledged: {m['acknowledged']}; team: all agents joined "
                      f"{team.get('all_agents_joined')}, {team.get('loops_accepted')} loops accepted",
                      f"wall time: recorded team {recorded_s:.0f} s, live team {live_s:.0f} s (the camera plays at 15 "
                      "Hz; the agent takes every frame in turn)",
                      "one run is one sample: the live team's keyframe order at the server depends on timing"]}
