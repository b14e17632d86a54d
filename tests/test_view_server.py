"""The viser viewer (skipped without the `view` extra): a run's scene as named nodes with layer checkboxes, the
page served over HTTP, redraws that drop what is gone, and the live view during a one-agent run and a team run."""

from __future__ import annotations

import urllib.request

import numpy as np
import pytest

from view_runs import write_team_run

pytest.importorskip("viser")

FAST = {"mapping": {"iterations": 4, "first_iterations": 8}, "tracking": {"refine": False},
        "keyframes": {"every": 1}, "loop_closure": {"min_index_gap": 2}}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    return generate(tmp_path_factory.mktemp("view_srv") / "d", GeneratorConfig.preset("tiny", frames=3))


@pytest.fixture
def viewer():
    from swarmsplat.slam.view.server import Viewer

    v = Viewer(port=0)
    yield v
    v.close()


def test_scene_nodes_layers_and_redraw(tmp_path, dataset, viewer):
    from swarmsplat.slam.view import load_scene

    write_team_run(tmp_path, dataset)
    scene = load_scene(tmp_path)
    viewer.show(scene)
    nodes = set(viewer.nodes())
    assert {"/global/map/map", "/global/slam/agent_0", "/global/slam/agent_1", "/global/gt/agent_0",
            "/global/no_lc/agent_1", "/global/keyframes/agent_0/1", "/global/intra/edges",
            "/global/inter/edges"} <= nodes
    assert set(viewer.layers()) == {"map", "slam", "no_lc", "gt", "keyframes", "intra", "inter"}
    assert viewer._panel.content.startswith(f"## {scene.title}")
    with urllib.request.urlopen(viewer.url, timeout=10) as r:
        assert r.status == 200 and b"<html" in r.read().lower()
    viewer.set_layer_visible("gt", False)
    assert viewer._groups["/global/gt"].visible is False and viewer._checks["layer:gt"].value is False
    scene.edges, scene.frusta = [], scene.frusta[:1]
    viewer.show(scene)
    gone = nodes - set(viewer.nodes())
    assert {"/global/intra/edges", "/global/inter/edges", "/global/keyframes/agent_1/0"} <= gone
    assert "/global/keyframes/agent_0/0" in viewer.nodes()


def test_other_frames_start_hidden(tmp_path, dataset, viewer):
    from swarmsplat.slam.view import load_scene

    write_team_run(tmp_path, dataset, joined=False)
    viewer.show(load_scene(tmp_path))
    assert viewer._frames["global"].visible is True and viewer._frames["agent_1"].visible is False
    assert "/agent_1/map/map_agent_1" in viewer.nodes()
    viewer.set_frame_visible("agent_1", True)
    assert viewer._frames["agent_1"].visible is True and viewer._checks["frame:agent_1"].value is True


def test_live_view_of_one_agent_then_its_folder(tmp_path, dataset, viewer):
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import run_sequence
    from swarmsplat.slam.view.live import LiveView

    live = LiveView(viewer, interval=0.0)
    sizes = []
    observe = lambda agent: (live(agent), sizes.append(len(viewer.nodes())))  # noqa: E731
    out = tmp_path / "run"
    run_sequence(dataset / "agent_0", out, SlamConfig().override(FAST), progress=False, observer=observe)
    assert live.updates == 3 and sizes[0] > 0
    assert {"/global/map/map", "/global/slam/agent_0", "/global/keyframes/agent_0/2"} <= set(viewer.nodes())
    assert "running" in viewer._panel.content
    live.finish(out)  # the finished run, from its files: ground truth now, and the metrics
    assert "/global/gt/agent_0" in viewer.nodes() and "PSNR" in viewer._panel.content


def test_live_view_of_a_team(dataset, viewer):
    from swarmsplat import kernels
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.progress import TeamRounds
    from swarmsplat.slam.dense.team.server import ServerConfig
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.view.live import LiveView

    seqs = load_dataset(dataset).agents
    cfg = SlamConfig().override(FAST)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in seqs], [s.name for s in seqs], cfg, ServerConfig(tau_sim=0.5))
    live = LiveView(viewer, interval=0.0)
    with TeamRounds(team, enabled=False, observer=live) as rounds:
        team.run(seqs, limits=[2, 2], progress=rounds)
    assert live.updates == 2
    nodes = set(viewer.nodes())
    assert {"/global/slam/agent_0", "/global/keyframes/agent_0/1"} <= nodes
    # Agents that have not joined are drawn in their own frame, hidden at first.
    for a, s in enumerate(team.server.slots):
        frame = "global" if s.component == 0 else seqs[s.component].name
        assert f"/{frame}/slam/{seqs[a].name}" in nodes
    T = team.trajectory(0)[1]
    drawn = viewer.scene.tracks[0]
    assert drawn.name == "agent_0_slam" and np.allclose(drawn.points, T[:, :3, 3])
    assert not live(team)  # nothing changed since the last redraw: no redraw
