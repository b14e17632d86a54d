"""`swarmsplat eval`: in-process through slam.cli.main (numbers, JSON, plot, one-line errors) and one subprocess."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, shared_data
from swarmsplat.kernels import se3
from swarmsplat.slam.cli import main
from swarmsplat.slam.io.trajectory import write_tum

EVO = "tum_trajectories_evo"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _ate_row(out: str) -> list[str]:
    rows = [l.split() for l in out.splitlines() if l.startswith("ATE")]
    assert len(rows) == 1, out
    return rows[0]


def test_eval_tum_prints_ate_and_writes_json_and_plot(tmp_path, capsys):
    gt, est = shared_data(EVO, "freiburg1_xyz-groundtruth.txt"), shared_data(EVO, "freiburg1_xyz-rgbdslam.txt")
    out = tmp_path / "res" / "metrics.json"
    rc = main(["eval", "--gt", str(gt), "--est", str(est), "--format", "tum", "--align", "se3", "--json", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    row = _ate_row(text)
    assert float(row[1]) == pytest.approx(0.013470, abs=1e-6) and row[-1] == "m"  # evo's number (PROVENANCE)
    data = json.loads(out.read_text())
    assert data["ate_rmse"] == pytest.approx(0.013470, abs=1e-6)
    assert data["rpe_rmse"] == pytest.approx(0.005764, abs=1e-6)
    assert data["matched"] == 785
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10_000
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temporary files left behind


def test_eval_sim3_monocular(tmp_path, capsys):
    gt, est = shared_data(EVO, "freiburg1_xyz-groundtruth.txt"), shared_data(EVO, "freiburg1_xyz-ORB_kf_mono.txt")
    assert main(["eval", "--gt", str(gt), "--est", str(est), "--align", "sim3", "--json", str(tmp_path / "m.json")]) == 0
    data = json.loads((tmp_path / "m.json").read_text())
    assert data["ate_rmse"] == pytest.approx(0.009755, abs=1e-6) and data["matched"] == 32
    assert data["scale"] == pytest.approx(1.1056223637370346, abs=1e-9)


def _traj(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return se3.exp(np.cumsum(rng.normal(0, 0.05, (n, 6)), axis=0))


def test_eval_kitti_by_index(tmp_path, capsys):
    T = _traj()
    noisy = T.copy()
    noisy[:, :3, 3] += np.random.default_rng(1).normal(0, 0.02, (len(T), 3))
    for name, P in (("gt.txt", T), ("est.txt", noisy)):
        (tmp_path / name).write_text("".join(" ".join(f"{v:.12f}" for v in M[:3].ravel()) + "\n" for M in P))
    assert main(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"), "--format", "kitti",
                 "--align", "none", "--json", str(tmp_path / "k.json")]) == 0
    data = json.loads((tmp_path / "k.json").read_text())
    want = np.sqrt(np.mean(np.sum((noisy[:, :3, 3] - T[:, :3, 3]) ** 2, axis=1)))
    assert data["matched"] == len(T) and data["ate_rmse"] == pytest.approx(want, abs=1e-9)


def test_eval_euroc_ground_truth_against_tum_estimate(tmp_path, capsys):
    T = _traj(30)
    t_ns = 1403636579763555584 + np.arange(30, dtype=np.int64) * 50_000_000
    xyz, q = se3.to_tum(T)
    (tmp_path / "data.csv").write_text("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n" + "".join(
        f"{t},{p[0]:.17g},{p[1]:.17g},{p[2]:.17g},{qq[3]:.17g},{qq[0]:.17g},{qq[1]:.17g},{qq[2]:.17g}\n" for t, p, qq in zip(t_ns, xyz, q)))
    write_tum(tmp_path / "est.txt", t_ns * 1e-9, T)
    assert main(["eval", "--gt", str(tmp_path / "data.csv"), "--gt-format", "euroc", "--est", str(tmp_path / "est.txt"),
                 "--est-format", "tum"]) == 0
    row = _ate_row(capsys.readouterr().out)
    assert float(row[1]) < 1e-6  # same poses; write_tum keeps 9 decimals


def _one_error_line(capsys):
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in cap.err, cap.err
    return err[0]


def test_eval_bad_inputs_one_line_nonzero(tmp_path, capsys):
    gt = shared_data(EVO, "freiburg1_xyz-groundtruth.txt")
    T = _traj(10)
    good = tmp_path / "good.txt"
    write_tum(good, np.arange(10) * 0.1, T)
    bad_line = tmp_path / "bad_line.txt"
    bad_line.write_text(good.read_text().replace(good.read_text().splitlines()[3], "0.3 1 2 3"))
    nan = tmp_path / "nan.txt"
    lines = good.read_text().splitlines()
    lines[5] = lines[5].split()[0] + " nan 0 0 0 0 0 1"
    nan.write_text("\n".join(lines) + "\n")
    kitti = tmp_path / "k.txt"
    kitti.write_text("".join(" ".join(f"{v:.9f}" for v in M[:3].ravel()) + "\n" for M in T))
    cases = [
        (["--gt", str(tmp_path / "missing.txt"), "--est", str(good)], "trajectory file not found"),
        (["--gt", str(good), "--est", str(bad_line)], "bad_line.txt:4: expected 8 numbers"),
        (["--gt", str(good), "--est", str(nan)], "nan.txt:6: NaN"),
        (["--gt", str(good), "--est", str(good), "--format", "csv"], "unknown trajectory format 'csv'"),
        (["--gt", str(good), "--est", str(good), "--align", "affine"], "unknown alignment 'affine'"),
        (["--gt", str(good), "--est", str(kitti)], "has no timestamps"),
        (["--gt", str(gt), "--est", str(good)], "no matching timestamps"),
    ]
    for extra, message in cases:
        out = tmp_path / "keep.json"
        out.write_text('{"ate_rmse": 1.0}')  # a previous result must survive a failed run untouched
        rc = main(["eval", *extra, "--json", str(out)])
        line = _one_error_line(capsys)
        assert rc == 2, (extra, line)
        assert line.startswith("swarmsplat eval: error:") and message in line, (message, line)
        assert out.read_text() == '{"ate_rmse": 1.0}'


def test_eval_subprocess_console_entry(tmp_path):
    gt, est = shared_data(EVO, "fr2_desk_groundtruth.txt"), shared_data(EVO, "fr2_desk_ORB.txt")
    r = subprocess.run([sys.executable, "-m", "swarmsplat.slam", "eval", "--gt", str(gt), "--est", str(est),
                        "--json", str(tmp_path / "o.json")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert float(_ate_row(r.stdout)[1]) == pytest.approx(0.008119, abs=1e-6)
    assert json.loads((tmp_path / "o.json").read_text())["ate_rmse"] == pytest.approx(0.008119, abs=1e-6)
    r = subprocess.run([sys.executable, "-m", "swarmsplat.slam", "eval", "--gt", str(tmp_path / "none.txt"), "--est", str(est)],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def _team(tmp_path, second_frame_differs: bool):
    gt_root, est_root = tmp_path / "data", tmp_path / "results"
    rng = np.random.default_rng(4)
    R, t = se3.so3_exp(rng.normal(0, 1, 3)), rng.normal(0, 1, 3)
    R2, t2 = se3.so3_exp(rng.normal(0, 1, 3)), rng.normal(0, 1, 3)
    for k, name in enumerate(["robot_a", "robot_b"]):
        T = _traj(30, seed=10 + k)
        stamps = 5.0 + np.arange(30) / 10
        write_tum(gt_root / name / "groundtruth.txt", stamps, T)
        RR, tt = (R2, t2) if (k == 1 and second_frame_differs) else (R, t)
        write_tum(est_root / f"{name}.txt", stamps, se3.make(RR, tt)[None] @ T)
    (gt_root / "dataset.yaml").write_text("name: two\nkind: rgbd\nagents: [robot_a, robot_b]\nseed: 3\n")
    return gt_root, est_root


@pytest.mark.parametrize("differs", [False, True])
def test_eval_team_folders(tmp_path, capsys, differs):
    gt_root, est_root = _team(tmp_path, differs)
    out = tmp_path / "team.json"
    assert main(["eval", "--gt", str(gt_root), "--est", str(est_root), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ATE team (one frame)" in text and "ATE robot_a" in text
    data = json.loads(out.read_text())
    assert set(data["per_agent"]) == {"robot_a", "robot_b"} and data["matched"] == 60
    assert max(v["ate_rmse"] for v in data["per_agent"].values()) < 1e-6  # each agent alone aligns exactly
    if differs:
        assert data["ate_rmse"] > 0.05  # one alignment cannot fit two frames
    else:
        assert data["ate_rmse"] < 1e-6
    assert out.with_suffix(".png").read_bytes()[:8] == PNG_MAGIC


def test_eval_team_needs_two_folders(tmp_path, capsys):
    gt_root, est_root = _team(tmp_path, False)
    rc = main(["eval", "--gt", str(gt_root), "--est", str(est_root / "robot_a.txt")])
    assert rc == 2 and "both folders" in _one_error_line(capsys)


def test_generated_dataset_loads_and_evaluates_end_to_end(tmp_path, capsys):
    """The generator's output (written by `swarmsplat generate`) read by our loaders and scored by eval."""
    pytest.importorskip("swarmsplat.slam.synthetic")
    from swarmsplat.slam.io.datasets import load_dataset

    data = tmp_path / "data"
    assert main(["generate", "--out", str(data), "--preset", "tiny", "--agents", "2", "--frames", "4", "--mono"]) == 0
    ds = load_dataset(data)
    assert ds.kind == "mono" and len(ds) == 2 and all(len(s) == 4 for s in ds.agents)
    f = ds.agents[1][3]
    assert f.depth is None and f.color.dtype == np.uint8 and f.T_world_cam_odom is not None
    est = tmp_path / "est"
    est.mkdir()
    for s in ds.agents:
        (est / f"{s.name}.txt").write_bytes((s.root / "odometry.txt").read_bytes())
    capsys.readouterr()
    assert main(["eval", "--gt", str(data), "--est", str(est), "--align", "sim3", "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["matched"] == 8 and set(m["per_agent"]) == {s.name for s in ds.agents}
    # Each odometry starts in its own frame: alone each aligns well, the team in one frame cannot.
    assert max(v["ate_rmse"] for v in m["per_agent"].values()) < m["ate_rmse"]
