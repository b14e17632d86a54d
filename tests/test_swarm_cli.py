"""`swarmsplat swarm` end to end on a tiny generated monocular dataset: every output is written and consistent;
bad input gives one error line."""

import json

import numpy as np
import pytest

from swarmsplat.slam.cli import main


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("swarm_cli") / "data"
    assert main(["generate", "--out", str(root), "--preset", "tiny", "--agents", "2", "--frames", "6", "--mono"]) == 0
    return root


def test_swarm_in_process_outputs(tiny, tmp_path, capsys):
    out = tmp_path / "run"
    sched = tmp_path / "s.yaml"
    sched.write_text("ticks: 12\nframes_per_tick: 1\nwindows:\n  - {start: 2, end: 12, robots: [0, 1]}\n")
    assert main(["swarm", str(tiny), "--out", str(out), "--stride", "2", "--schedule", str(sched),
                 "--formulation", "ss"]) == 0
    assert "merged ATE" in capsys.readouterr().out
    for name in ("agent_0.txt", "agent_1.txt", "odometry/agent_0.txt", "metrics.json", "trajectories.png",
                 "pose_graph_optimized.g2o", "vocabulary.npz"):
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    assert m["formulation"] == "ss" and m["schedule"]["ticks"] == 12
    assert set(m["ate"]["per_robot_rmse"]) == {"agent_0", "agent_1"}
    for r in ("agent_0", "agent_1"):
        b = m["bytes"][r]
        assert b["sent_bytes"]["Hello"] > 0 and b["sent_bytes"]["Descriptors"] > 0 and b["rejected"] == 0
        assert b["sent_total"] == sum(b["sent_bytes"].values())
        assert m["images_bytes"][r]["keyframes"] == 3
    rows = np.loadtxt(out / "agent_0.txt")
    assert rows.shape == (3, 8) and np.all(np.isfinite(rows))
    # both robots ended with the same estimate (the optimiser's broadcast)
    assert m["estimate_stamp"]["agent_0"] == m["estimate_stamp"]["agent_1"] is not None


def test_swarm_bad_schedule_one_line(tiny, tmp_path, capsys):
    sched = tmp_path / "s.yaml"
    sched.write_text("ticks: -1\n")
    assert main(["swarm", str(tiny), "--out", str(tmp_path / "o"), "--schedule", str(sched)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s.yaml" in err[0]
