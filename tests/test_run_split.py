"""`swarmsplat run SEQUENCE --split 0:3,3:5`: one recording run as a team of agents on frame ranges; bad ranges
are one-line user errors (exit code 2) that name the flag and the bad range."""

from __future__ import annotations

import json

import pytest

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.cli import main
from swarmsplat.slam.io.datasets.split import parse_ranges

from conftest import shared_data


def test_parse_ranges():
    assert parse_ranges("0:3,3:5") == [(0, 3), (3, 5)]
    assert parse_ranges(" 0:3 , 2: ") == [(0, 3), (2, None)]
    assert parse_ranges(":2,2:4,4:") == [(None, 2), (2, 4), (4, None)]
    for bad, match in [("", "expected"), ("0:3,", "expected"), ("0-3,3:5", "'0-3' is not a frame range"),
                       ("0:3,x:5", "'x:5'"), ("3:1,0:2", "'3:1' is empty"), ("2:2,0:1", "empty"),
                       ("0:5", "at least two ranges"), ("-1:3,3:5", "'-1:3'")]:
        with pytest.raises(InputError, match=match):
            parse_ranges(bad)


@pytest.mark.parametrize("split, message", [("3:1,0:2", "--split: range '3:1' is empty"),
                                            ("0:3", "at least two ranges"),
                                            ("0:3,3:9", r"--split: frame range \[3, 9\) is not inside sequence")])
def test_bad_split_is_a_user_error(tmp_path, capsys, split, message):
    import re

    data = shared_data("redwood_livingroom1_rgbd5")
    assert main(["run", str(data), "--out", str(tmp_path / "o"), "--split", split, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("swarmsplat run: error: ") and re.search(message, err), err
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_split_of_a_multi_agent_dataset_is_refused(tmp_path, capsys):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "data", GeneratorConfig.preset("tiny", frames=2))
    assert main(["run", str(data), "--out", str(tmp_path / "o"), "--split", "0:1,1:2", "--quiet"]) == 2
    assert "already holds 2 agents" in capsys.readouterr().err


def test_run_split_of_a_real_sequence(tmp_path, capsys):
    """The Redwood living-room frames as two agents with disjoint frames through the CLI (0-2 and 3-4): the second
    agent joins the first one's frame through an inter-agent loop, and the team is tracked close to the ground truth.
    Agent 1's two positions cannot be aligned on their own, so its ATE is scored under the team's one alignment."""
    data = shared_data("redwood_livingroom1_rgbd5")
    cfg = tmp_path / "fast.yaml"
    cfg.write_text(FAST_YAML)
    out = tmp_path / "run"
    assert main(["run", str(data), "--out", str(out), "--split", "0:3,3:", "--config", str(cfg), "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [(a["name"], a["frames"]) for a in printed["agents"]] == [("agent_0", 3), ("agent_1", 2)]
    assert all(a["in_global_frame"] for a in printed["agents"])
    assert printed["loops"]["inter"]["accepted"] >= 1
    assert printed["ate_rmse_team"] is not None and printed["ate_rmse_team"] < ATE_BOUND_M
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["components"] == {"agent_0": ["agent_0", "agent_1"]}
    a0, a1 = saved["agents"]
    assert a0["ate_rmse"] < ATE_BOUND_M and a0["ate_rmse_no_lc"] is not None
    assert a1["ate_align"] == "joint" and a1["ate_rmse"] < ATE_BOUND_M and a1["ate_rmse_no_lc"] is None
    assert "not aligned on its own" in a1["ate_note"]


# Few mapping iterations, every frame a keyframe (2-3 frames per agent): this checks the split and the join, not
# the map. The ATE bound is explained in tests/test_team_real.py.
FAST_YAML = """
mapping: {iterations: 8, first_iterations: 25}
tracking: {refine: false}
keyframes: {every: 1}
loop_closure: {min_index_gap: 2}
"""
ATE_BOUND_M = 0.02
