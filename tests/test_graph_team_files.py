"""Multi-robot graph readers: DPGO's robotN/measurements.csv and one g2o per robot (graph.dpgo_csv, team_files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_data

from swarmsplat.graph.dpgo_csv import COLUMNS
from swarmsplat.graph.g2o import write_g2o
from swarmsplat.graph.pose_graph import PoseGraph, key_index, key_robot, robot_key
from swarmsplat.graph.team_files import read_team
from swarmsplat.kernels.errors import InputError

HEADER = ",".join(COLUMNS)


def _row(rs, ps, rd, pd, t=(1.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0), kappa=10000, tau=100, inlier=1):
    return f"{rs},{ps},{rd},{pd},{q[0]},{q[1]},{q[2]},{q[3]},{t[0]},{t[1]},{t[2]},{kappa},{tau},{inlier},1"


def _team(tmp_path: Path, rows0=None, rows1=None, header=HEADER) -> Path:
    """Two robots of 4 poses, one inter-robot loop (0,3)-(1,0) in both files."""
    loop = _row(0, 3, 1, 0, t=(0.5, 1.0, 0.0), inlier=0)
    r0 = [_row(0, i, 0, i + 1) for i in range(3)] + [loop] if rows0 is None else rows0
    r1 = [_row(1, i, 1, i + 1) for i in range(3)] + [loop] if rows1 is None else rows1
    for n, rows in ((0, r0), (1, r1)):
        d = tmp_path / "team" / f"robot{n}"
        d.mkdir(parents=True, exist_ok=True)
        (d / "measurements.csv").write_text("\n".join([header] + rows) + "\n")
    return tmp_path / "team"


def test_measurements_folder_reads_as_one_team(tmp_path):
    g = read_team([_team(tmp_path)])
    assert len(g.poses) == 8 and len(g.odometry()) == 6
    assert len(g.loops()) == 1  # the two copies of the inter-robot row kept once
    e = g.loops()[0]
    assert (key_robot(e.key_i), key_index(e.key_i), key_robot(e.key_j), key_index(e.key_j)) == ("a", 3, "b", 0)
    assert np.allclose(np.diag(e.info), [20000] * 3 + [100] * 3)  # diag(2 kappa I, tau I)
    assert np.allclose(g.poses[robot_key("a", 3)][:3, 3], [3, 0, 0])  # odometry chained from the identity


@pytest.mark.parametrize("case, expect", [
    ("missing column", r"robot0/measurements.csv:1: column 'tau' missing"),
    ("non-unit quaternion", r"robot0/measurements.csv:3: fields qx,qy,qz,qw: quaternion has norm 2"),
    ("pose id gap", r"robot0/measurements.csv:3: field pose_src: pose 2 of robot 0 has no odometry row from pose 1"),
    ("unknown robot", r"robot0/measurements.csv:5: field robot_dst is 7, a robot with no robot7"),
    ("disagreeing copies", r"robot1/measurements.csv:5: field ty is 2, but the copy of this inter-robot row at "
                           r".*robot0/measurements.csv:5 has 1"),
    ("not a number", r"robot0/measurements.csv:2: field qw is 'abc', not a number"),
    ("foreign row", r"robot0/measurements.csv:5: fields robot_src,robot_dst are 1,1"),
    ("short row", r"robot0/measurements.csv:3: 14 fields, the header has 15"),
    ("empty file", r"robot1/measurements.csv:1: empty file, expected the header robot_src,pose_src"),
])
def test_bad_measurements_name_file_line_and_field(tmp_path, case, expect):
    odo0 = [_row(0, i, 0, i + 1) for i in range(3)]
    loop = _row(0, 3, 1, 0, t=(0.5, 1.0, 0.0), inlier=0)
    kw = {}
    if case == "missing column":
        kw["header"] = HEADER.replace(",tau", "")
    elif case == "non-unit quaternion":
        kw["rows0"] = [odo0[0], _row(0, 1, 0, 2, q=(0, 0, 0, 2)), odo0[2], loop]
    elif case == "pose id gap":
        kw["rows0"] = [odo0[0], _row(0, 2, 0, 3), loop]
    elif case == "unknown robot":
        kw["rows0"] = odo0 + [_row(0, 3, 7, 0)]
    elif case == "disagreeing copies":
        kw["rows1"] = [_row(1, i, 1, i + 1) for i in range(3)] + [_row(0, 3, 1, 0, t=(0.5, 2.0, 0.0), inlier=0)]
    elif case == "not a number":
        kw["rows0"] = [odo0[0].replace(",1.0,", ",abc,", 1)] + odo0[1:] + [loop]
    elif case == "foreign row":
        kw["rows0"] = odo0 + [_row(1, 0, 1, 1)]
    elif case == "short row":
        kw["rows0"] = [odo0[0], odo0[1].rsplit(",", 1)[0], odo0[2], loop]
    folder = _team(tmp_path, **kw)
    if case == "empty file":
        (folder / "robot1" / "measurements.csv").write_text("")
    with pytest.raises(InputError, match=expect) as e:
        read_team([folder])
    assert "\n" not in str(e.value)


def _robot_graph(name: str, other: str, n: int = 3) -> PoseGraph:
    g = PoseGraph()
    info = np.eye(6)
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = i
        g.add_pose(robot_key(name, i), T)
    for i in range(n - 1):
        T = np.eye(4)
        T[0, 3] = 1.0
        g.add_odometry(robot_key(name, i), robot_key(name, i + 1), T, info)
    return g


def test_per_robot_g2o_files_check_their_inter_robot_copies(tmp_path):
    a, b = _robot_graph("a", "b"), _robot_graph("b", "a")
    T = np.eye(4)
    T[1, 3] = 2.0
    for g in (a, b):
        g.pending.append(type(a.odometry()[0])(robot_key("a", 2), robot_key("b", 0), T.copy(), np.eye(6)))
    fa, fb = tmp_path / "0.g2o", tmp_path / "1.g2o"
    _write_with_pending(a, fa)
    _write_with_pending(b, fb)
    g = read_team([tmp_path])  # a folder of <k>.g2o
    assert len(g.poses) == 6 and len(g.loops()) == 1
    b.pending[0].T_ij[1, 3] = 2.5
    _write_with_pending(b, fb)
    with pytest.raises(InputError, match=r"1.g2o:\d+: translation of edge a2-b0 differs from its copy at .*0.g2o:\d+"):
        read_team([fa, fb])
    with pytest.raises(InputError, match=r"0.g2o:\d+: edge a2-b0 goes to pose b0 of a robot none of the files"):
        read_team([fa, tmp_path / "0.g2o"])


def _write_with_pending(g: PoseGraph, path: Path) -> None:
    """write_g2o writes edges between the graph's own poses; DGS files also hold the edges to other robots."""
    write_g2o(g, path)
    p = [3, 4, 5, 0, 1, 2]
    iu = np.triu_indices(6)
    with open(path, "a") as f:
        for e in g.pending:
            xyz = e.T_ij[:3, 3]
            f.write(f"EDGE_SE3:QUAT {e.key_i} {e.key_j} {xyz[0]} {xyz[1]} {xyz[2]} 0 0 0 1 "
                    + " ".join(f"{v:g}" for v in e.info[np.ix_(p, p)][iu]) + "\n")


def test_shared_multirobot_graphs_read():
    g = read_team([shared_data("kimera_multi_outdoor_6robots")])
    assert len(g.poses) == 1076 and len(g.odometry()) == 1070
    assert sum(e.inter_robot for e in g.edges) == 109 and len(g.loops()) == 122
    g = read_team([shared_data("dgs_multirobot", "blocks_world", "16robots")])
    assert len(g.robots()) == 16 and len(g.components()) == 1 and not g.pending


def test_graph_solve_distributed_on_a_measurements_folder(tmp_path):
    import json

    from swarmsplat.slam.cli import main

    folder = _team(tmp_path)
    assert main(["graph", "solve", str(folder), "--out", str(tmp_path / "c.g2o"), "--solver", "gnc"]) == 0
    assert main(["graph", "solve", str(folder), "--out", str(tmp_path / "d.g2o"), "--solver", "gnc",
                 "--distributed"]) == 0
    central = json.loads((tmp_path / "c.json").read_text())
    d = json.loads((tmp_path / "d.json").read_text())
    assert set(d["distributed"]) >= {"robots", "iterations", "bytes_total", "bytes_per_separator_iteration",
                                     "gather_bytes"}
    assert d["distributed"]["robots"] == 2 and d["rejected_loops"] == central["rejected_loops"] == []
    # nothing rejected, every weight 1: the truncated objective is the plain error (no loop above the threshold)
    assert central["tls_objective"] == pytest.approx(central["final_error"], rel=1e-9)
    assert d["final_error"] <= central["final_error"] * 1.01 + 1e-9
    assert d["distributed"]["sparse_tol"] == 1e-3
    assert main(["graph", "solve", str(folder), "--out", str(tmp_path / "e.g2o"), "--solver", "gnc",
                 "--distributed", "--sparse-tol", "0"]) == 0
    every = json.loads((tmp_path / "e.json").read_text())["distributed"]
    assert every["sparse_tol"] == 0.0 and every["bytes_total"] >= d["distributed"]["bytes_total"]


def test_a_disconnected_team_is_solved_per_group_and_reported(tmp_path):
    """Two robots that never met: each is solved in its own frame (anchored at its first pose), centralised and
    distributed alike, and the JSON lists the groups."""
    import json

    from swarmsplat.slam.cli import main

    folder = _team(tmp_path, rows0=[_row(0, i, 0, i + 1) for i in range(3)],
                   rows1=[_row(1, i, 1, i + 1) for i in range(3)])
    g = read_team([folder])
    assert len(g.components()) == 2 and g.anchors() == [robot_key("a", 0), robot_key("b", 0)]
    for flags, name in (([], "c"), (["--distributed"], "d")):
        assert main(["graph", "solve", str(folder), "--out", str(tmp_path / f"{name}.g2o"), *flags]) == 0
        out = json.loads((tmp_path / f"{name}.json").read_text())
        assert out["final_error"] <= 1e-9 and out["components"] == 2  # odometry alone: nothing to disagree with
    assert out["distributed"]["groups"] == [[0], [1]]
