"""`swarmsplat export`: a run folder as a ROS bag of standard messages (slam.io.bags.export), read back with
rosbags: every pose equals the run's trajectory file, keyframes and loop edges are there, for one agent and for a
team (keyframes and loops from its pose graph)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from swarmsplat.kernels import se3  # noqa: E402
from swarmsplat.kernels.errors import InputError  # noqa: E402
from swarmsplat.slam.io.bags.export import export_run  # noqa: E402
from swarmsplat.slam.io.bags.sequence import open_reader  # noqa: E402
from swarmsplat.slam.io.trajectory import read_tum, write_tum  # noqa: E402


def _path(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    T = [np.eye(4)]
    for _ in range(n - 1):
        T.append(T[-1] @ se3.exp(rng.normal(0, [0.02, 0.02, 0.02, 0.05, 0.05, 0.05])))
    return np.arange(n) / 30.0, np.stack(T)


def _read(bag: Path) -> dict[str, list]:
    reader = open_reader(bag)
    try:
        out: dict[str, list] = {}
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
        return out
    finally:
        reader.close()


def _T(pose) -> np.ndarray:
    q, p = pose.orientation, pose.position
    return se3.make(se3.quat_wxyz_to_matrix(np.array([q.w, q.x, q.y, q.z])), np.array([p.x, p.y, p.z]))


@pytest.fixture
def single_run(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    t, T = _path(12, 0)
    write_tum(run / "trajectory.txt", t, T)
    write_tum(run / "trajectory_no_lc.txt", t, T @ se3.exp(np.array([0.0, 0.0, 0.01, 0, 0, 0])))
    write_tum(run / "keyframes.txt", t[::4], T[::4])
    (run / "metrics.json").write_text('{"agent": "cam"}')
    (run / "loops.csv").write_text("query_kf,match_kf,accepted\n2,0,True\n2,1,False\n")
    return run, t, T


@pytest.mark.parametrize("to", ["mcap", "rosbag2", "rosbag1"])
def test_a_single_agent_run_as_a_bag(single_run, tmp_path, to):
    run, t, T = single_run
    bag = tmp_path / ("out.bag" if to == "rosbag1" else "out")
    counts = export_run(run, bag, to)
    assert counts == {"/cam/pose": 12, "/cam/pose_tracking": 12, "/tf": 12, "/cam/path": 1, "/cam/keyframes": 1,
                      "/loops": 1}
    msgs = _read(bag)
    got = np.stack([_T(m.pose) for _, m in msgs["/cam/pose"]])
    np.testing.assert_allclose(got, T, atol=1e-9)
    stamps = read_tum(run / "trajectory.txt")[0]  # the file's stamps (microseconds)
    assert [rec for rec, _ in msgs["/cam/pose"]] == [int(round(s * 1e9)) for s in stamps]
    tf = msgs["/tf"][3][1].transforms[0]
    assert tf.child_frame_id == "cam/camera" and tf.header.frame_id == "map"
    (_, kf), = msgs["/cam/keyframes"]
    assert len(kf.poses) == 3
    (_, loops), = msgs["/loops"]
    (marker,) = loops.markers
    assert marker.type == 5 and len(marker.points) == 2  # one accepted loop: kf 2 -> kf 0
    assert np.allclose([marker.points[0].x, marker.points[0].y, marker.points[0].z], T[8][:3, 3])


def test_a_team_run_takes_keyframes_and_loops_from_its_pose_graph(tmp_path):
    from swarmsplat.graph.pose_graph import Edge, PoseGraph, robot_key
    from swarmsplat.graph.g2o import write_g2o

    run = tmp_path / "team"
    g = PoseGraph()
    for a, name in enumerate(("alpha", "beta")):
        t, T = _path(9, a + 1)
        write_tum(run / "trajectories" / f"{name}.txt", t, T)
        write_tum(run / "trajectories_no_lc" / f"{name}.txt", t, T)
        for k in range(3):
            g.add_pose(robot_key("ab"[a], k), T[3 * k])
            if k:
                g.add_edge(Edge(robot_key("ab"[a], k - 1), robot_key("ab"[a], k), np.eye(4), np.eye(6), "odometry"))
    g.add_edge(Edge(robot_key("a", 0), robot_key("a", 2), np.eye(4), np.eye(6)))  # intra
    g.add_edge(Edge(robot_key("a", 1), robot_key("b", 2), np.eye(4), np.eye(6)))  # inter
    write_g2o(g, run / "pose_graph_optimized.g2o")
    counts = export_run(run, tmp_path / "out", "mcap")
    assert counts["/alpha/pose"] == 9 and counts["/beta/keyframes"] == 1 and counts["/tf"] == 18
    msgs = _read(tmp_path / "out")
    (_, loops), = msgs["/loops"]
    assert sorted(m.ns for m in loops.markers) == ["loops_inter", "loops_intra"]
    (_, kf), = msgs["/beta/keyframes"]
    np.testing.assert_allclose(_T(kf.poses[2].pose), read_tum(run / "trajectories" / "beta.txt")[1][6], atol=1e-9)


def test_export_refuses_what_it_cannot_write(single_run, tmp_path, capsys):
    from swarmsplat.slam.cli import main

    run, *_ = single_run
    with pytest.raises(InputError, match="not a run folder"):
        export_run(tmp_path, tmp_path / "x", "mcap")
    (tmp_path / "taken").mkdir()
    with pytest.raises(InputError, match="exists already"):
        export_run(run, tmp_path / "taken", "mcap")
    assert main(["export", str(run), "--to", "zip"]) == 2
    assert "--to 'zip': expected one of mcap, rosbag2, rosbag1" in capsys.readouterr().err
    assert main(["export", str(run)]) == 0 and (run / "bag_mcap" / "metadata.yaml").is_file()


def test_an_mcap_export_reads_with_foxglove_readers(single_run, tmp_path):
    """Foxglove's own MCAP readers (`mcap`, `mcap-ros2-support`), not rosbags: every message decodes with the
    schemas the file carries (ros2msg), the summary and footer are there, the poses are the trajectory file's."""
    pytest.importorskip("mcap")
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    run, *_ = single_run
    counts = export_run(run, tmp_path / "out", "mcap")
    (path,) = (tmp_path / "out").glob("*.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == sum(counts.values())
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        decoded: dict[str, list] = {}
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(msg)
        f.seek(-8, 2)
        assert f.read(8) == b"\x89MCAP0\r\n"  # the closing magic, after the footer
    assert {k: len(v) for k, v in decoded.items()} == counts
    got = np.stack([_T(m.pose) for m in decoded["/cam/pose"]])
    np.testing.assert_allclose(got, read_tum(run / "trajectory.txt")[1], atol=5e-10)
    assert decoded["/tf"][0].transforms[0].child_frame_id == "cam/camera"
    assert decoded["/loops"][0].markers[0].type == 5
