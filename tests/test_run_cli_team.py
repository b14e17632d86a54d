"""`swarmsplat run` on a multi-agent dataset dispatches to the team."""

import json

from swarmsplat.slam.cli import main
from swarmsplat.slam.synthetic import GeneratorConfig, generate


def test_run_on_a_multi_agent_dataset_writes_team_outputs(tmp_path, capsys):
    data = generate(tmp_path / "data", GeneratorConfig.preset("tiny"))
    out = tmp_path / "run"
    assert main(["run", str(data), "--out", str(out), "--frames", "3", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [a["name"] for a in printed["agents"]] == ["agent_0", "agent_1"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["agents"]) == 2
    for a in metrics["agents"]:
        assert 0 <= a["ate_rmse"] < 0.05 and "ate_rmse_no_lc" in a
    for name in ("loops.csv", "pose_graph_initial.g2o", "pose_graph_optimized.g2o", "map.ply", "config.yaml"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "trajectories").iterdir()) == ["agent_0.txt", "agent_1.txt"]
