"""`swarmsplat demo` end to end on the tiny preset: dataset generated (then reused), team run, report written."""

from __future__ import annotations

import json


def test_demo_tiny_end_to_end(tmp_path):
    from slam.cli import main
    from slam.demo import ensure_dataset

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--preset", "tiny", "--quiet"]) == 0
    res = out / "results"
    m = json.loads((res / "metrics.json").read_text())
    assert len(m["agents"]) == 2
    for a in m["agents"]:
        assert a["frames_tracked"] == 10
        assert a["ate_rmse"] is not None and a["ate_rmse_no_lc"] is not None
    assert m["psnr"] is not None and m["render_views"] > 0
    for f in ("report.md", "loops.csv", "map.ply", "pose_graph_optimized.g2o", "trajectory.png", "renders.png"):
        assert (res / f).is_file(), f
    report = (res / "report.md").read_text()
    assert "## Trajectory accuracy" in report and "## Loop closures" in report
    # The cached dataset is reused when the settings match.
    stamp = (out / "dataset" / "dataset.yaml").stat().st_mtime_ns
    assert ensure_dataset(out / "dataset", "tiny", progress=False) == out / "dataset"
    assert (out / "dataset" / "dataset.yaml").stat().st_mtime_ns == stamp
