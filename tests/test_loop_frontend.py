"""The FLOCC loop front-end (ratio gate and confidence) and `swarmsplat pairs` on a small rendered mono dataset."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from swarmsplat.graph.confidence import correspondence_ratio, loop_confidence
from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair.classical import ClassicalRegistrar
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose
from swarmsplat.slam.flocc.frontend import LoopFrontend

CAM = default_camera(240, 180)


def _write_mono_dataset(root, agents: dict[str, list[np.ndarray]], room: TexturedRoom):
    """Our folder format, monocular: rgb/, rgb.txt, odometry.txt, groundtruth.txt, calibration.yaml."""
    import cv2
    import yaml

    from swarmsplat.slam.io.trajectory import write_tum

    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump({"name": "rendered", "kind": "mono", "agents": list(agents)}))
    for name, poses in agents.items():
        d = root / name
        (d / "rgb").mkdir(parents=True)
        stamps = np.arange(len(poses), dtype=float)
        lines = ["# timestamp filename"]
        for i, T in enumerate(poses):
            cv2.imwrite(str(d / "rgb" / f"{i:06d}.png"), room.render(T, CAM)[0][..., ::-1])
            lines.append(f"{stamps[i]:.6f} rgb/{i:06d}.png")
        (d / "rgb.txt").write_text("\n".join(lines) + "\n")
        (d / "calibration.yaml").write_text(yaml.safe_dump(CAM.to_dict()))
        write_tum(d / "groundtruth.txt", stamps, np.stack(poses))
        # odometry in the agent's own frame (starts at identity): what a VIO would report
        write_tum(d / "odometry.txt", stamps, se3.inverse(poses[0]) @ np.stack(poses))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    room = TexturedRoom(seed=7)
    a = [look_pose((0.0, 0.0, -1.0 + 0.25 * i), 5.0 * i) for i in range(5)]  # walks forward, turning right
    b = [look_pose((0.6, 0.0, -0.9 + 0.25 * i), 10.0 + 5.0 * i) for i in range(4)]  # a similar path, offset
    root = tmp_path_factory.mktemp("mono")
    _write_mono_dataset(root, {"alpha": a, "beta": b}, room)
    return root


def _frontend(images: dict, registrar=None):
    return LoopFrontend(registrar or ClassicalRegistrar(), lambda a, i: images[a][i], lambda a: CAM,
                        lambda a: len(images[a]))


def test_frontend_ratio_gate_and_confidence_use_graph_confidence():
    room = TexturedRoom(seed=7)
    images = {"a": [room.render(look_pose((0, 0, 0.2 * i)), CAM)[0] for i in range(3)],
              "b": [room.render(look_pose((0.3, 0.0, 0.3), 8.0), CAM)[0],
                    TexturedRoom(seed=8).render(look_pose((0, 0, 0), 180.0), CAM)[0]]}
    fe = _frontend(images)
    good = fe.evaluate(("a", 2), ("b", 0), similarity=0.5)
    assert good.odom_pair == (1, 2) and good.loop.success
    r = correspondence_ratio(good.loop.n_correspondences, good.odom.n_correspondences)
    assert good.ratio == pytest.approx(r)
    assert good.accepted and good.p == pytest.approx(loop_confidence(r)) and 0 < good.p < 1
    bad = fe.evaluate(("a", 2), ("b", 1), similarity=0.2)  # another room
    assert not bad.accepted and bad.p is None and bad.reason
    assert fe.encode_calls == 4  # a1, a2, b0, b1: a2 and the odometry pair are encoded once, then cached
    # an encoding received from its owner is used as is, never recomputed
    other = _frontend(images)
    other.put_encoding(("b", 0), fe.encodings[("b", 0)])
    assert other.has_encoding(("b", 0)) and not other.has_encoding(("b", 1))
    again = other.evaluate(("a", 2), ("b", 0))
    assert other.encode_calls == 2 and again.loop.n_correspondences == good.loop.n_correspondences
    with pytest.raises(InputError, match="expected an Encoding"):
        other.put_encoding(("b", 1), b"bytes")
    first = fe.evaluate(("a", 0), ("b", 0))
    assert first.odom_pair == (0, 1)  # the first keyframe borrows the next one
    # a tighter gate rejects what a permissive one accepts, with the reason
    strict = _frontend(images)
    strict.r_thr = 10.0
    res = strict.evaluate(("a", 2), ("b", 0))
    assert not res.accepted and "R_thr" in res.reason and res.ratio == pytest.approx(good.ratio)


def test_r_thr_defaults_per_pair_backend():
    from swarmsplat.graph.confidence import R_THR_DEFAULT
    from swarmsplat.slam.flocc.frontend import default_r_thr

    assert default_r_thr("classical") == 0.15  # measured: perf/results/fig5-cpu.md
    assert default_r_thr("xfeat") == 0.25  # measured with the same sweep (python -m perf.flocc_fig5 --quick)
    assert default_r_thr("mast3r") == R_THR_DEFAULT == 0.3  # the paper's value, for its dense matches
    assert default_r_thr("something-new") == R_THR_DEFAULT
    fe = _frontend({"a": [], "b": []})
    assert fe.r_thr == 0.15
    explicit = LoopFrontend(fe.registrar, fe.image_of, fe.camera_of, fe.num_keyframes, r_thr=0.4)
    assert explicit.r_thr == 0.4


def test_frontend_single_keyframe_agent_is_rejected_cleanly():
    room = TexturedRoom(seed=7)
    images = {"a": [room.render(look_pose((0, 0, 0)), CAM)[0]], "b": [room.render(look_pose((0.2, 0, 0)), CAM)[0]]}
    res = _frontend(images).evaluate(("a", 0), ("b", 0))
    assert not res.accepted and "single keyframe" in res.reason


def test_pairs_command_writes_every_candidate_with_ground_truth_errors(dataset, tmp_path):
    from swarmsplat.slam.cli import main

    out = tmp_path / "pairs.csv"
    assert main(["pairs", str(dataset), "--out", str(out), "--quiet", "--save-vocabulary",
                 str(tmp_path / "voc.npz")]) == 0
    rows = list(csv.DictReader(out.open()))
    from swarmsplat.slam.run.pairs import COLUMNS

    assert rows and list(rows[0]) == COLUMNS
    keys = {frozenset([(r["query_agent"], r["query_index"]), (r["match_agent"], r["match_index"])]) for r in rows}
    assert len(keys) == len(rows)  # each unordered pair once
    assert all(float(r["similarity"]) >= 0.1 for r in rows)
    acc = [r for r in rows if r["accepted"] == "1"]
    assert acc, "no loop accepted on overlapping paths"
    for r in acc:
        assert float(r["rot_err_deg"]) < 3.0 and float(r["t_dir_err_deg"]) < 15.0
        assert 0.0 < float(r["p"]) < 1.0 and float(r["ratio"]) >= 0.3
        q = np.array([float(r[k]) for k in ("qx", "qy", "qz", "qw")])
        assert math.isclose(np.linalg.norm(q), 1.0, rel_tol=1e-5)
        assert math.isclose(np.linalg.norm([float(r[k]) for k in ("tx", "ty", "tz")]), 1.0, rel_tol=1e-4)
    assert (tmp_path / "voc.npz").is_file()
    # the saved vocabulary reproduces the same candidates
    out2 = tmp_path / "pairs2.csv"
    assert main(["pairs", str(dataset), "--out", str(out2), "--quiet", "--place-checkpoint",
                 str(tmp_path / "voc.npz")]) == 0
    assert [r["similarity"] for r in csv.DictReader(out2.open())] == [r["similarity"] for r in rows]


def test_pairs_command_errors_are_one_line(dataset, tmp_path, capsys):
    from swarmsplat.slam.cli import main

    assert main(["pairs", str(dataset), "--out", str(tmp_path / "x.csv"), "--backend", "mast3r", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "checkpoint" in err and "\n" not in err
    assert main(["pairs", str(tmp_path / "missing"), "--out", str(tmp_path / "x.csv")]) == 2
    assert main(["pairs", str(dataset), "--out", str(tmp_path / "x.csv"), "--place", "dbow3"]) == 2
    assert not (tmp_path / "x.csv").exists()
    from swarmsplat.slam.run.pairs import run_pairs

    with pytest.raises(InputError, match="stride"):
        run_pairs(dataset, tmp_path / "x.csv", stride=0)


def test_inlier_precision_recall_ranks_detectors():
    from swarmsplat.slam.run.pairs import inlier_precision_recall

    rows = [{"success": "1", "t_err_m_gt_scale": str(err), "ratio": str(r), "similarity": str(s)}
            for err, r, s in [(0.1, 0.9, 0.2), (0.5, 0.8, 0.9), (5.0, 0.2, 0.8), (0.3, 0.7, 0.1), (9.0, 0.1, 0.7)]]
    rows.append({"success": "0", "t_err_m_gt_scale": "", "ratio": "0.05", "similarity": "0.95"})  # not registered
    by_ratio = inlier_precision_recall(rows, "ratio")
    by_sim = inlier_precision_recall(rows, "similarity")
    assert by_ratio["n"] == 5 and by_ratio["n_inliers"] == 3
    assert by_ratio["ap"] == pytest.approx(1.0)  # the ratio puts all three inliers first
    assert by_sim["ap"] < by_ratio["ap"]
    assert by_ratio["recall"][-1] == pytest.approx(1.0) and by_ratio["precision"][-1] == pytest.approx(3 / 5)
    assert inlier_precision_recall([], "ratio")["n"] == 0
