"""A team member on live ROS 2 topics killed (SIGKILL) mid-stream and started again with `--resume`, over real Zenoh
on localhost: it tracks again the frames it had logged since its checkpoint (slam.run.checkpoint.frame_log), then
the ones that arrive now, and its server takes it back with every frame and keyframe once. Skipped without
eclipse-zenoh or rosbags."""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from test_live_zenoh import _cdr, _free_port  # noqa: E402
from test_team_link import FAST  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FRAMES = 16


def _play(store, seq, port: int, frames: range, stop: threading.Event) -> None:
    """The robot's camera driver on `port`: once the agent subscribes to its topics, `frames` at 10 Hz."""
    from swarmsplat.slam.io.live import zenoh_config

    _, conf = zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])
    robot = zenoh.open(conf)
    keys = {"info": "camera/color/camera_info", "color": "camera/color/image_raw", "depth": "camera/depth/image_raw"}
    # blocking like a reliable ROS 2 publisher: the default (drop) loses an image when the link is busy
    block = zenoh.CongestionControl.BLOCK
    pubs = {kind: robot.declare_publisher(key, congestion_control=block) for kind, key in keys.items()}
    try:
        t_end = time.time() + 120  # a put before the agent's subscription is known goes nowhere: wait for it
        while time.time() < t_end and not stop.is_set() and not all(p.matching_status.matching for p in pubs.values()):
            time.sleep(0.1)
        for i in frames:
            if stop.is_set():
                break
            for kind, pub in pubs.items():
                pub.put(_cdr(store, seq, i, kind))
            time.sleep(0.1)
    finally:
        for p in pubs.values():
            p.undeclare()
        robot.close()


def _logged(out: Path) -> list[int]:
    return sorted(int(p.stem) for p in (out / "progress" / "frames").glob("*.npz") if p.stem.isdigit())


def test_a_killed_live_team_member_resumes_and_its_server_keeps_every_frame_once(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    from swarmsplat.slam.cli import main
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "d", GeneratorConfig.preset("tiny", agents=1, frames=FRAMES))
    seq = load_sequence(data / "agent_0")
    store = get_typestore(Stores.ROS2_HUMBLE)
    cfg = SlamConfig().override({**FAST, "submaps": {"max_keyframes": 2}, "checkpoint": {"every_submaps": 1}})
    (tmp_path / "cfg.yaml").write_text(cfg.to_yaml())
    out, ckpt = tmp_path / "robot", tmp_path / "robot" / "progress" / "checkpoint.pkl"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    server_at = f"tcp/127.0.0.1:{_free_port()}"
    cli = [sys.executable, "-m", "swarmsplat.slam"]
    server = subprocess.Popen([*cli, "server", "--agents", "1", "--out", str(tmp_path / "team"), "--config",
                               str(tmp_path / "cfg.yaml"), "--listen", server_at, "--quiet", "--ros-keys", "off"],
                              env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    member = ["agent", "zenoh/", "--server", server_at, "--id", "0", "--name", "robot", "--out", str(out),
              "--config", str(tmp_path / "cfg.yaml"), "--idle-timeout", "60", "--camera-timeout", "60", "--quiet"]
    port = _free_port()
    agent = subprocess.Popen([*cli, *member, "--listen", f"tcp/127.0.0.1:{port}"], env=env, cwd=REPO,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stop = threading.Event()
    driver = threading.Thread(target=_play, args=(store, seq, port, range(0, 12), stop),
                              daemon=True)
    driver.start()
    try:
        t_end = time.time() + 180
        while time.time() < t_end and agent.poll() is None:  # a checkpoint, and frames tracked after it
            if ckpt.is_file():
                with open(ckpt, "rb") as f:
                    kept = pickle.load(f)["next_frame"]
                if _logged(out) and _logged(out)[-1] >= kept + 1:
                    break
            time.sleep(0.05)
        agent.send_signal(signal.SIGKILL)  # a hard kill: nothing is written on the way out
        assert agent.wait(timeout=30) == -signal.SIGKILL, "the agent ended before it could be killed"
    finally:
        stop.set()
        if agent.poll() is None:
            agent.kill()
        driver.join(timeout=10)
    with open(ckpt, "rb") as f:
        kept = pickle.load(f)["next_frame"]
    logged = _logged(out)
    assert logged[0] == kept and logged == list(range(kept, logged[-1] + 1)), (kept, logged)  # none before the checkpoint
    before = logged[-1] + 1  # frames the killed process read: 0 .. before - 1

    port = _free_port()
    stop = threading.Event()
    driver = threading.Thread(target=_play, args=(store, seq, port, range(12, FRAMES), stop),
                              daemon=True)
    driver.start()
    try:
        assert main([*member, "--listen", f"tcp/127.0.0.1:{port}", "--frames", str(FRAMES - 12), "--resume"]) == 0
        out_s = server.communicate(timeout=180)[0]
    finally:
        stop.set()
        driver.join(timeout=10)
        if server.poll() is None:
            server.kill()
    assert server.returncode == 0, out_s[-3000:]

    # the agent: the frames before the kill, then the new ones, each once; nothing left to resume from
    stamps = np.array([float(ln.split()[0]) for ln in (out / "trajectory.txt").read_text().splitlines()
                       if ln and not ln.startswith("#")])
    expected = np.concatenate([seq.timestamps[:before], seq.timestamps[12:FRAMES]])
    np.testing.assert_allclose(stamps, expected, atol=1e-6)
    assert not ckpt.exists() and not _logged(out)
    assert json.loads((out / "link.json").read_text())["acknowledged"]
    # the server: the same frames once, every keyframe once (made twice after the checkpoint, kept once)
    team = json.loads((tmp_path / "team" / "metrics.json").read_text())
    assert team["status"] == "complete", team
    robot = {a["name"]: a for a in team["agents"]}["robot"]
    assert robot["frames_tracked"] == len(expected), robot
    link = team["link"]["agents"]["robot"]
    journal = [ln for ln in (out / "progress" / "poses.tum").read_text().splitlines() if ln and ln[0] != "#"]
    assert len({ln.split()[0] for ln in journal}) == len(journal)  # the journal holds each frame once
    assert link["keyframes"] == robot["keyframes"] >= 2, (link, robot)
