"""graph/: g2o reading and writing, bad input with line numbers, multi-robot merge (DGS), the graph CLI."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data

from swarmsplat.graph.formulations import build_problem
from swarmsplat.graph.g2o import read_g2o, write_g2o
from swarmsplat.graph.pose_graph import PoseGraph, key_index, key_robot, robot_key
from swarmsplat.graph.solvers import levenberg_marquardt
from swarmsplat.kernels.errors import InputError

V0 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
V1 = "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
INFO = " ".join(str(v) for v in np.eye(6)[np.triu_indices(6)])
E01 = f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO}\n"


def _write(tmp_path, text, name="g.g2o"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8", errors="surrogateescape")  # \udcXX: the raw byte XX
    return p


def test_roundtrip_preserves_poses_edges_and_information(tmp_path):
    rng = np.random.default_rng(0)
    g = PoseGraph()
    for i in range(4):
        T = np.eye(4)
        T[:3, 3] = rng.normal(size=3)
        g.add_pose(robot_key("b", i), T)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)  # full, with off-diagonal translation-rotation blocks
    for i in range(3):
        g.add_odometry(robot_key("b", i), robot_key("b", i + 1), np.linalg.inv(g.poses[robot_key("b", i)])
                       @ g.poses[robot_key("b", i + 1)], info)
    g.add_loop(robot_key("b", 0), robot_key("b", 3), np.eye(4), info)
    out = write_g2o(g, tmp_path / "rt.g2o")
    h = read_g2o(out)
    assert sorted(h.poses) == sorted(g.poses)
    assert all(np.allclose(h.poses[k], g.poses[k], atol=1e-9) for k in g.poses)
    assert [(e.key_i, e.key_j, e.kind) for e in h.edges] == [(e.key_i, e.key_j, e.kind) for e in g.edges]
    assert all(np.allclose(a.info, b.info, rtol=1e-9) for a, b in zip(h.edges, g.edges))
    assert key_robot(h.keys()[0]) == "b" and key_index(h.keys()[-1]) == 3


@pytest.mark.parametrize("text, line, what", [
    (V0 + V1 + "EDGE_SE3:FOO 0 1\n", 3, "unknown g2o element"),
    (V0 + "VERTEX_SE3:QUAT 1 1 0 0\n", 2, "needs 8 values"),
    (V0 + V1 + E01.replace("EDGE_SE3:QUAT 0 1", "EDGE_SE3:QUAT 0 7"), 3, "does not define"),
    (V0 + V1 + E01.replace(INFO, INFO.replace("1.0", "-1.0", 1)), 3, "not positive definite"),
    (V0 + "VERTEX_SE3:QUAT 1 nan 0 0 0 0 0 1\n" + E01, 2, "NaN"),
    (V0 + V1 + E01.replace("0 0 0 1 1.0", "0 0 0 1 nan", 1), 3, "NaN"),
    (V0 + V1 + "# comment\n" + E01.replace("0 0 0 1 1.0", "0 0 0 0 1.0", 1), 4, "quaternion"),
    (V0 + "\udc89PNG\n", 2, "not a text g2o file"),  # a byte that is not UTF-8 (written back as 0x89)
])
def test_bad_input_names_file_and_line(tmp_path, text, line, what):
    p = _write(tmp_path, text)
    with pytest.raises(InputError, match=what) as err:
        read_g2o(p)
    assert f"{p}:{line}:" in str(err.value)


def test_se2_files_read_and_solve():
    g = read_g2o(shared_data("se_sync_2d_small", "CSAIL.g2o"))  # no VERTEX lines: poses from a spanning tree
    assert g.is_2d and len(g.poses) == 1045 and len(g.edges) == 1172
    res = levenberg_marquardt(build_problem(g))
    assert res.final_error < res.initial_error


def test_dgs_multirobot_files_load_and_merge():
    root = shared_data("dgs_multirobot", "blocks_world", "4robots")
    parts = [read_g2o(root / f"{r}.g2o") for r in range(4)]
    assert all(p.pending for p in parts)  # each robot's file holds its inter-robot edges
    merged = parts[0]
    for p in parts[1:]:
        merged = merged.merged(p)
    full = read_g2o(root / "fullGraph.g2o")
    assert not merged.pending and len(merged.components()) == 1
    assert merged.robots() == ["a", "b", "c", "d"]
    assert (len(merged.poses), len(merged.edges)) == (len(full.poses), len(full.edges))
    e_merged = levenberg_marquardt(build_problem(merged)).final_error
    e_full = levenberg_marquardt(build_problem(full)).final_error
    assert e_merged == pytest.approx(e_full, rel=1e-5)  # same graph, different ids


def test_cli_graph_solve(tmp_path, capsys):
    from swarmsplat.slam.cli import main

    a = shared_data("kimera_rpgo_two_robot", "robot_a.g2o")
    b = shared_data("kimera_rpgo_two_robot", "robot_b.g2o")
    out = tmp_path / "out.g2o"
    assert main(["graph", "solve", str(a), str(b), "--out", str(out), "--solver", "gnc"]) == 0
    text = capsys.readouterr().out
    final = float(text.split("final error ")[1].split()[0])
    g = read_g2o(out)
    assert len(g.poses) == 92 and "rejected loops" in text
    assert final < float(text.split("initial error ")[1].split()[0])
    bad = _write(tmp_path, V0 + "FOO 1\n", "bad.g2o")
    assert main(["graph", "solve", str(bad), "--out", str(tmp_path / "x.g2o")]) == 2
    assert "bad.g2o:2" in capsys.readouterr().err
    assert not (tmp_path / "x.g2o").exists()
