"""A team member on live ROS 2 topics, over real Zenoh on localhost: `swarmsplat server` serves two agents, one
on a recording (`swarmsplat agent DATA --server ...`, its own process) and one on live topics (this process:
slam.run.team_link.live_agent, fed CDR images as the Zenoh-ROS 2 bridge names them). The live agent tracks every
frame it receives, publishes each pose back, journals its poses, and the server takes its keyframes without
waiting for it and writes the team's outputs. Skipped without eclipse-zenoh or rosbags."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

from test_live_zenoh import _cdr, _connected, _free_port  # noqa: E402
from test_team_link import FAST  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SPLIT = "0:5,2:8"


def test_a_live_agent_is_a_team_member(tmp_path):
    from rosbags.typesys import Stores, get_typestore

    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence
    from swarmsplat.slam.io.live import PosePublisher, ZenohRos2Source, zenoh_config
    from swarmsplat.slam.io.trajectory import read_tum
    from swarmsplat.slam.metrics.ate import ate
    from swarmsplat.slam.run.team_link.live_agent import run_live_team_agent
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=8))
    cfg = SlamConfig().override(FAST)
    (tmp_path / "cfg.yaml").write_text(cfg.to_yaml())
    live_seq = split_sequence(load_dataset(data).agents[0], parse_ranges(SPLIT)).agents[1]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    port = _free_port()
    server_at = f"tcp/127.0.0.1:{port}"
    cli = [sys.executable, "-m", "swarmsplat.slam"]
    server = subprocess.Popen([*cli, "server", "--agents", "2", "--out", str(tmp_path / "team"), "--config",
                               str(tmp_path / "cfg.yaml"), "--dataset", str(data), "--split", SPLIT, "--listen",
                               server_at, "--quiet"], env=env, cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    from swarmsplat.slam.run.team_link.registry import ask_index

    # no --id: the server gives the index by name (the name of its dataset's second sequence: 1)
    assert ask_index("agent_1", connect=[server_at], timeout=60) == 1
    assert ask_index("agent_1", connect=[server_at], timeout=60) == 1  # asked again: the same
    viewer = _TeamViewer.open(port)  # a ROS 2 client on the server's endpoint, before any agent sends
    recorded = subprocess.Popen([*cli, "agent", str(data), "--split", SPLIT, "--id", "0", "--server", server_at,
                                 "--config", str(tmp_path / "cfg.yaml"), "--quiet"], env=env, cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    store = get_typestore(Stores.ROS2_HUMBLE)
    cam_port = _free_port()
    src = ZenohRos2Source("", name="robot_b", listen=[f"tcp/127.0.0.1:{cam_port}"])
    _, conf = zenoh_config(connect=[f"tcp/127.0.0.1:{cam_port}"])
    robot = zenoh.open(conf)
    poses: list[bytes] = []
    sub = robot.declare_subscriber("swarmsplat/robot_b/pose", lambda s: poses.append(s.payload.to_bytes()))
    try:
        _connected(src.session, robot)

        def camera_driver():  # a reliable publisher (rmw_zenoh's RELIABLE QoS blocks rather than drops): a loaded
            # machine's Zenoh would otherwise drop images, and this test is about the team, not a lossy link
            block = zenoh.CongestionControl.BLOCK
            for i in range(len(live_seq)):
                robot.put("camera/color/camera_info", _cdr(store, live_seq, i, "info"), congestion_control=block)
                robot.put("camera/color/image_raw", _cdr(store, live_seq, i, "color"), congestion_control=block)
                robot.put("camera/depth/image_raw", _cdr(store, live_seq, i, "depth"), congestion_control=block)
                time.sleep(1 / 15)

        driver = threading.Thread(target=camera_driver, daemon=True)
        driver.start()
        m = run_live_team_agent(src, 1, cfg, name="robot_b", connect=[server_at],
                                publisher=PosePublisher(src.session, "swarmsplat/robot_b/pose"),
                                max_frames=len(live_seq), camera_timeout=30, idle_timeout=30, progress=False,
                                out=tmp_path / "robot_b")
        driver.join()
        time.sleep(0.3)
    finally:
        sub.undeclare()
        robot.close()
        src.close()
        try:
            out_r = recorded.communicate(timeout=180)[0]
            out_s = server.communicate(timeout=180)[0]
        finally:
            for p in (recorded, server):
                if p.poll() is None:
                    p.kill()
            if viewer is not None:
                time.sleep(0.5)
                viewer.close()
    assert m["reason"] == "max_frames" and m["frames_tracked"] == len(live_seq), m
    assert m["acknowledged"] and m["poses_published"] == len(live_seq) and len(poses) == len(live_seq)
    assert recorded.returncode == 0, out_r
    assert server.returncode == 0, out_s
    team = json.loads((tmp_path / "team" / "metrics.json").read_text())
    assert team["status"] == "complete"
    by_name = {a["name"]: a for a in team["agents"]}
    assert by_name["robot_b"]["frames_tracked"] == len(live_seq) and by_name["robot_b"]["keyframes"] >= 2
    assert team["link"]["agents"]["robot_b"]["bytes_total"] > 0 and not team["link"]["lost_agents"]
    # the team server published, the way rmw_zenoh does, every agent's corrected trajectory, the merged map and the
    # loops: a ROS 2 client received every message it sent
    sent = team["link"]["ros2"]["sent"]
    assert viewer is None or viewer.counts() == {team["link"]["ros2"]["topics"][r]: k for r, k in sent.items()}, (viewer.counts(), sent)
    assert all(sent.get(f"path:{a['name']}", 0) >= 1 for a in team["agents"]) and sent["map"] >= 1
    assert viewer is None or len(viewer.last["/swarmsplat/team/robot_b/path"].poses) == by_name["robot_b"]["keyframes"]
    # the live agent's own folder: its pose journal up to its last keyframe, and its trajectory as corrected
    journal = [ln for ln in (tmp_path / "robot_b" / "progress" / "poses.tum").read_text().splitlines()
               if ln and not ln.startswith("#")]
    assert 2 <= len(journal) <= len(live_seq)
    traj = (tmp_path / "robot_b" / "trajectory.txt").read_text().splitlines()
    assert len([ln for ln in traj if not ln.startswith("#")]) == len(live_seq)

    # it joined the team: in the recorded agent's frame (one component), where its poses meet the truth
    others = [a for a in team["agents"] if a["name"] != "robot_b"]
    assert team["all_agents_joined"] and team["loops_accepted"] >= 1, team
    assert by_name["robot_b"]["in_global_frame"] and by_name["robot_b"]["component"] == others[0]["component"]
    assert by_name["robot_b"]["ate_rmse"] < 0.03, by_name["robot_b"]
    # the poses it published live: one per frame, at that frame's timestamp, where the frame was (a few cm of the
    # truth after one rigid alignment; the scene is ~2 m across), and the ones its journal keeps
    stamps, T_pub = _decode_poses(store, poses)
    np.testing.assert_allclose(stamps, live_seq.timestamps, atol=1e-6)
    assert np.all(np.isfinite(T_pub)) and np.allclose(T_pub[:, 3], [0, 0, 0, 1])
    live_ate = ate(live_seq.timestamps, live_seq.gt_poses, stamps, T_pub).stats.rmse
    assert live_ate < 0.03, live_ate
    j_stamps, T_journal = read_tum(tmp_path / "robot_b" / "progress" / "poses.tum")
    np.testing.assert_allclose(j_stamps, stamps[:len(j_stamps)], atol=1e-6)
    np.testing.assert_allclose(T_journal[:, :3, 3], T_pub[:len(j_stamps), :3, 3], atol=1e-5)


class _TeamViewer:
    """zenoh-ros2-sdk (a client nobody here wrote) subscribed to the team server's topics; a plain Zenoh session
    (the test then checks what the server says it sent, without it)."""

    TOPICS = {"/swarmsplat/team/agent_0/path": "nav_msgs/msg/Path", "/swarmsplat/team/robot_b/path":
              "nav_msgs/msg/Path", "/swarmsplat/team/map": "sensor_msgs/msg/PointCloud2",
              "/swarmsplat/team/loops": "visualization_msgs/msg/MarkerArray"}

    @classmethod
    def open(cls, port: int):
        try:
            import zenoh_ros2_sdk  # noqa: F401
        except ImportError:
            return None
        return cls(port)

    def __init__(self, port: int):
        from zenoh_ros2_sdk import ROS2Subscriber, message_registry

        self.got: dict[str, list] = {t: [] for t in self.TOPICS}
        message_registry._registry = message_registry.MessageRegistry(str(Path(__file__).parent / "ros2_definitions"))
        self.subs = [ROS2Subscriber(t, m, (lambda msg, t=t: self.got[t].append(msg)), node_name="team_viewer",
                                    router_port=port) for t, m in self.TOPICS.items()]
        time.sleep(1.0)

    def counts(self) -> dict:
        return {t: len(v) for t, v in self.got.items() if v}

    @property
    def last(self) -> dict:
        return {t: v[-1] for t, v in self.got.items() if v}

    def close(self) -> None:
        from zenoh_ros2_sdk import message_registry
        from zenoh_ros2_sdk.session import ZenohSession

        for s in self.subs:
            s.close()
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        ZenohSession._instance = None
        message_registry._registry = None


def _decode_poses(store, payloads: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [N] s, T_world_cam [N, 4, 4]) of CDR geometry_msgs/PoseStamped messages."""
    from swarmsplat.kernels.se3 import quat_wxyz_to_matrix

    stamps, T = [], []
    for b in payloads:
        msg = store.deserialize_cdr(b, "geometry_msgs/msg/PoseStamped")
        p, q = msg.pose.position, msg.pose.orientation
        M = np.eye(4)
        M[:3, :3] = quat_wxyz_to_matrix(np.array([q.w, q.x, q.y, q.z]))
        M[:3, 3] = [p.x, p.y, p.z]
        stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
        T.append(M)
    return np.array(stamps), np.array(T)


def test_an_agent_without_an_id_and_no_server_says_so(tmp_path, capsys):
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=3))
    t0 = time.monotonic()
    assert main(["agent", str(data / "agent_0"), "--name", "robot_x", "--server", f"tcp/127.0.0.1:{_free_port()}",
                 "--set", "link.connect_timeout_s=2", "--quiet"]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("swarmsplat agent:")]
    assert len(err) == 1 and "robot_x: no team server answered within 2 s" in err[0], err
    assert time.monotonic() - t0 < 30
