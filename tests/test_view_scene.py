"""Building what `swarmsplat view` shows from a run folder, without viser or a browser: splat covariances, ground
truth brought into the map frame by the metrics' alignment, tracking-only trajectories aligned, keyframe frusta
from the calibration, loop edges per kind, agents outside the global frame, and one-line errors for bad folders."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from view_runs import KF_FRAMES, N_GAUSSIANS, write_single_run, write_team_run


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    return generate(tmp_path_factory.mktemp("view_data") / "d", GeneratorConfig.preset("tiny", frames=4))


def test_splat_covariance_is_rotated_scale_squared():
    from swarmsplat.slam.view.scene import splats_from_params
    from view_runs import gaussians

    s = splats_from_params("m", gaussians(3))
    np.testing.assert_allclose(s.covariances[0], np.diag([0.04, 0.01, 0.09]), atol=1e-6)  # 90° about z swaps x, y
    np.testing.assert_allclose(s.covariances[1], np.eye(3) * 0.15 ** 2, atol=1e-6)
    np.testing.assert_allclose(s.opacities[:, 0], 1 / (1 + np.exp(-3.0)), atol=1e-6)
    np.testing.assert_allclose(s.rgbs, [[1, 0, 0]] * 3, atol=1e-6)
    assert s.centers.shape == (3, 3) and s.opacities.shape == (3, 1)


def test_team_run_scene(tmp_path, dataset):
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.view import load_scene
    from swarmsplat.slam.view.scene import GLOBAL, LOOP_COLORS, agent_color

    est = write_team_run(tmp_path, dataset)
    scene = load_scene(tmp_path)
    assert [len(s) for s in scene.splats] == [N_GAUSSIANS] and scene.frames() == [GLOBAL]
    tracks = {t.name: t for t in scene.tracks}
    assert set(tracks) == {f"agent_{a}_{k}" for a in (0, 1) for k in ("slam", "no_lc", "gt")}
    for a in (0, 1):
        slam_pts = tracks[f"agent_{a}_slam"].points
        np.testing.assert_allclose(slam_pts, est[f"agent_{a}"][:, :3, 3], atol=1e-6)
        # Ground truth lives in another frame (A_MAP away); drawn in the map frame it lies on the estimate.
        gt_world = load_dataset(dataset).agents[a].gt_poses[:, :3, 3]
        assert np.abs(gt_world - slam_pts).max() > 0.1
        np.testing.assert_allclose(tracks[f"agent_{a}_gt"].points, slam_pts, atol=1e-5)
        np.testing.assert_allclose(tracks[f"agent_{a}_no_lc"].points, slam_pts, atol=1e-5)
        assert tracks[f"agent_{a}_slam"].color == agent_color(a)
    assert agent_color(0) != agent_color(1)
    # Keyframe frusta at the optimised poses, with the dataset's field of view (160x120, the generator's hfov).
    cam = load_dataset(dataset).agents[0].camera
    for f in scene.frusta:
        np.testing.assert_allclose(f.poses, est[f.agent][list(KF_FRAMES)], atol=1e-6)
        assert f.fov == pytest.approx(2 * np.arctan(0.5 * cam.height / cam.fy)) and f.aspect == pytest.approx(4 / 3)
    # One accepted loop of each kind, between the right keyframes; the rejected one is not drawn.
    edges = {e.kind: e for e in scene.edges}
    assert set(edges) == {"intra", "inter"} and edges["intra"].color != edges["inter"].color
    assert edges["intra"].color == LOOP_COLORS["intra"]
    e0, e1 = est["agent_0"], est["agent_1"]
    np.testing.assert_allclose(edges["intra"].segments[0], [e0[KF_FRAMES[1], :3, 3], e0[KF_FRAMES[0], :3, 3]],
                               atol=1e-5)
    np.testing.assert_allclose(edges["inter"].segments[0], [e1[KF_FRAMES[0], :3, 3], e0[KF_FRAMES[1], :3, 3]],
                               atol=1e-5)
    assert len(edges["inter"].segments) == 1
    assert "1.23" in scene.panel and "2.34" in scene.panel  # agent_0's ATE and the team's, in cm
    assert not scene.notes


def test_agent_outside_the_global_frame(tmp_path, dataset):
    from swarmsplat.slam.view import load_scene
    from swarmsplat.slam.view.scene import GLOBAL

    est = write_team_run(tmp_path, dataset, joined=False)
    scene = load_scene(tmp_path)
    assert scene.frames() == [GLOBAL, "agent_1"]
    assert {s.name: s.frame for s in scene.splats} == {"map": GLOBAL, "map_agent_1": "agent_1"}
    assert {t.frame for t in scene.tracks if t.agent == "agent_1"} == {"agent_1"}
    gt1 = next(t for t in scene.tracks if t.name == "agent_1_gt")
    np.testing.assert_allclose(gt1.points, est["agent_1"][:, :3, 3], atol=1e-5)  # aligned in its own frame
    assert [e.kind for e in scene.edges] == ["intra"]
    assert any("agent_1" in n for n in scene.notes)


def test_single_agent_run_and_demo_layout(tmp_path, dataset):
    from swarmsplat.slam.view import find_run, load_scene

    run = tmp_path / "demo" / "results"
    run.mkdir(parents=True)
    T = write_single_run(run, dataset / "agent_0")
    assert find_run(tmp_path / "demo") == run
    scene = load_scene(tmp_path / "demo")
    assert [t.kind for t in scene.tracks] == ["slam", "gt"]
    np.testing.assert_allclose(scene.tracks[1].points, T[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(scene.frusta[0].poses, T[list(KF_FRAMES)], atol=1e-6)
    assert [(e.kind, len(e.segments)) for e in scene.edges] == [("intra", 1)]


def test_dataset_gone_means_no_ground_truth_but_a_note(tmp_path, dataset):
    import json

    from swarmsplat.slam.view import load_scene

    write_team_run(tmp_path, dataset)
    m = json.loads((tmp_path / "metrics.json").read_text())
    m["dataset"] = str(tmp_path / "moved_away")
    (tmp_path / "metrics.json").write_text(json.dumps(m))
    scene = load_scene(tmp_path)
    assert {t.kind for t in scene.tracks} == {"slam", "no_lc"}
    assert any("moved_away" in n for n in scene.notes)
    # Without ground truth the tracking-only trajectory starts where the loop-closed one does.
    t = {x.name: x.points for x in scene.tracks}
    np.testing.assert_allclose(t["agent_0_no_lc"][0], t["agent_0_slam"][0], atol=1e-6)


def _view(args, capsys) -> tuple[int, str]:
    from swarmsplat.slam.cli import main

    code = main(["view", *map(str, args)])
    return code, capsys.readouterr().err.strip()


def test_bad_folders_are_one_line_errors(tmp_path, capsys, dataset):
    code, err = _view([tmp_path / "nowhere"], capsys)
    assert code == 2 and err == f"swarmsplat view: error: run folder not found: {tmp_path / 'nowhere'}"
    code, err = _view([tmp_path], capsys)
    assert code == 2 and "is not a run folder: no metrics.json" in err and len(err.splitlines()) == 1
    write_team_run(tmp_path, dataset, with_map=False)
    code, err = _view([tmp_path], capsys)
    assert code == 2 and "the run has no map" in err and len(err.splitlines()) == 1
    (tmp_path / "metrics.json").write_text("{not json")
    code, err = _view([tmp_path], capsys)
    assert code == 2 and "metrics.json: not readable JSON" in err


def test_port_in_use_is_a_one_line_error(tmp_path, capsys, dataset):
    write_team_run(tmp_path, dataset)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        code, err = _view([tmp_path, "--port", port], capsys)
    assert code == 2 and err == (f"swarmsplat view: error: --port {port} is in use on 127.0.0.1; "
                                 f"choose another with --port")



def test_screenshot_without_chromium_is_one_line(tmp_path, capsys, monkeypatch, dataset):
    monkeypatch.setenv("SWARMSPLAT_CHROMIUM", str(tmp_path / "no_such_browser"))
    write_team_run(tmp_path / "run", dataset)
    code, err = _view([tmp_path / "run", "--screenshot", tmp_path / "s.png"], capsys)
    assert code == 1 and err.startswith("swarmsplat view: error: --screenshot needs Chromium")
    assert len(err.splitlines()) == 1 and not (tmp_path / "s.png").exists()


def test_without_the_view_extra_one_line_says_how_to_get_it(tmp_path, capsys, monkeypatch, dataset):
    import sys

    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` now raises ImportError
    write_team_run(tmp_path, dataset)
    code, err = _view([tmp_path, "--port", "0"], capsys)
    assert code == 1 and err == "swarmsplat view: error: the viewer needs the 'viser' package: pip install -e '.[view]'"
