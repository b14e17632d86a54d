"""The team server's cloud route (slam.dense.team.cloud_route): two agents' local maps registered as point clouds
without an initial guess and checked by rendering — a true pair gives the true relative pose, a pair from another
world is refused with a reason, a window without depth is a reason (never an exception), and two real recordings
of different places never join (a dataset.yaml that names an agent folder in the Redwood layout)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.registration.global_registration import kiss_matcher_available
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.loops.loop_log import INTER, LoopRecord
from swarmsplat.slam.dense.team.server import ServerConfig
from swarmsplat.slam.io.datasets import load_dataset
from swarmsplat.slam.io.datasets.split import split_sequence, sub_sequence
from swarmsplat.slam.run.team import Team

from conftest import shared_data
from test_team import FAST  # few iterations: these tests check the route's logic, not the map


@pytest.fixture(scope="module")
def unjoined(tmp_path_factory):
    """A generated walk split into two agents that share views (frames 0-8 and 5-15), plus a third agent in
    another world; inter-agent loop search off, so the test drives the cloud route itself."""
    from swarmsplat import kernels
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("wide")
    seq = load_dataset(generate(root / "w0", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=16))).agents[0]
    other = load_dataset(generate(root / "w1", GeneratorConfig.preset("tiny", seed=1, agents=1, frames=6))).agents[0]
    ds = split_sequence(seq, [(0, 9), (5, 16)])
    agents = [*ds.agents, sub_sequence(other, 0, 6, "agent_2")]
    cfg = SlamConfig().override(FAST)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in agents], [s.name for s in agents], cfg, ServerConfig(inter_loops=False))
    team.run(agents)
    return team, agents


def _record(team, a, q, b, m) -> LoopRecord:
    return LoopRecord(INTER, team.agents[a].name, q.id, q.frame_index, team.agents[b].name, m.id, m.frame_index, 1.0)


def _gt_match_query(agents, a, q, b, m):
    Tq, Tm = agents[a].gt_poses[q.frame_index], agents[b].gt_poses[m.frame_index]
    return se3.inverse(Tm) @ Tq


@pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher wheel not installed (x86-64 only)")
def test_cloud_route_finds_the_true_pose_without_a_start(unjoined):
    team, agents = unjoined
    srv = team.server
    assert srv.components() == {0: [0], 1: [1], 2: [2]}
    q = team.agents[1].keyframes[1]  # frame 7 of the walk
    m = team.agents[0].keyframes[-1]  # frame 8
    rec = _record(team, 1, q, 0, m)
    srv.verify_cloud(rec, 1, q, 0, m, "no image start (test)")
    assert rec.route == "cloud" and rec.reason_code in ("unconfirmed", "accepted"), rec.reason
    assert rec.render_agree > 0.5 and rec.render_violate < 0.15
    L = srv.pending[-1] if srv.pending else srv.inter[-1]
    E = se3.inverse(_gt_match_query(agents, 1, q, 0, m)) @ L.T_ij
    assert np.linalg.norm(E[:3, 3]) < 0.05 and np.degrees(se3.rotation_angle(E[:3, :3])) < 2.0
    st = srv.clouds.stats()
    assert st["registrations"] >= 1 and st["windows_built"] >= 2


def test_cloud_route_refuses_another_world(unjoined):
    team, _ = unjoined
    srv = team.server
    q, m = team.agents[2].keyframes[-1], team.agents[0].keyframes[1]
    rec = _record(team, 2, q, 0, m)
    srv.verify_cloud(rec, 2, q, 0, m, "no image start (test)")
    assert not rec.accepted and rec.reason_code in ("registration", "fitness", "rmse", "render"), rec.reason
    assert "cloud route" in rec.reason


def test_a_window_without_depth_is_a_reason_not_an_exception(unjoined):
    from swarmsplat.slam.dense.loops.local_clouds import WindowRegistrar

    team, _ = unjoined
    ag = team.agents[0]
    reg = WindowRegistrar(radius=0)
    kf = ag.keyframes[0]
    blank = type("Blank", (), {"depth": np.zeros_like(kf.small.depth), "camera": kf.small.camera})()
    saved, kf.small = kf.small, blank
    try:
        w = reg.window("k", ag.keyframes, ag.gmap, kf, max_depth=10.0)
    finally:
        kf.small = saved
    assert w is None
    out = reg.register(w, reg.window("j", ag.keyframes, ag.gmap, ag.keyframes[1], max_depth=10.0))
    assert out.T_match_query is None and "too few depth points in the query window" in out.reason


def test_cloud_route_budget_per_keyframe(unjoined):
    team, _ = unjoined
    srv = team.server
    q = team.agents[1].keyframes[0]
    srv.cloud_tries[(1, q.id)] = team.agents[1].cfg.loop_closure.cloud_per_keyframe
    assert not srv.cloud_allowed(1, q)


def test_cloud_route_between_joined_agents_is_a_fallback(unjoined, monkeypatch):
    """Between agents in one frame the route runs only while no loop of the query keyframe was accepted; between
    agents in two frames it stays the way to join them."""
    team, _ = unjoined
    srv = team.server
    monkeypatch.setattr(team.agents[1].cfg.loop_closure, "cloud_route", True)
    monkeypatch.setattr(srv, "records", list(srv.records))
    monkeypatch.setattr(srv, "cloud_tries", {})
    q = team.agents[1].keyframes[2]
    assert srv.cloud_allowed(1, q, same=True)
    rec = _record(team, 1, q, 0, team.agents[0].keyframes[0])
    srv.records.append(rec)
    assert srv.cloud_allowed(1, q, same=True)  # being checked, not accepted
    rec.accepted = True
    assert not srv.cloud_allowed(1, q, same=True)
    assert srv.cloud_allowed(1, q, same=False)
    srv.records.append(_record(team, 1, team.agents[1].keyframes[3], 0, team.agents[0].keyframes[0]))
    assert srv.cloud_allowed(1, q, same=True)  # a later keyframe's records: q's are no longer the newest


@pytest.mark.slow
def test_two_real_recordings_of_different_places_never_join(tmp_path):
    """Redwood's living room (its own layout, named by dataset.yaml) and the HoloLens office: every candidate
    between them goes through the cloud route (the cameras differ) and none is accepted."""
    from swarmsplat.slam.run.team import run_team

    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "living").symlink_to(shared_data("redwood_livingroom1_211"))
    (tmp_path / "data" / "office").symlink_to(shared_data("hololens_office_85_378"))
    (tmp_path / "data" / "dataset.yaml").write_text("name: two places\nkind: rgbd\nagents: [living, office]\n")
    ds = load_dataset(tmp_path / "data")
    assert [s.name for s in ds.agents] == ["living", "office"]
    cfg = SlamConfig().override({**FAST, "map_refine": {"iterations_per_keyframe": 0}})
    m = run_team(ds, tmp_path / "out", cfg, limits=[40, 40], stride=2, progress=False, render_views=1)
    assert m["components"] == {"living": ["living"], "office": ["office"]}
    assert m["loops"]["inter"]["accepted"] == 0 and m["joins"]["made"] == 0
    cloud = m["inter_verify"]["cloud_route"]
    assert cloud["inter"]["candidates"] > 0, "different cameras: the cloud route must have been tried"
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Agents in separate frames" in report and "living" in report and "office" in report
    json.loads((tmp_path / "out" / "metrics.json").read_text())


@pytest.mark.slow
def test_cloud_route_never_accepts_a_pose_between_different_worlds(tmp_path):
    """A sweep for false joins: eight generated worlds (one agent each, 6 frames), every pair of agents from
    different worlds offered to the cloud route on two keyframe pairs; none may pass the clouds' gates and the
    render check (56 hypotheses between procedural rooms of one style: boxes, walls, similar textures)."""
    from swarmsplat import kernels
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    seqs = [sub_sequence(load_dataset(generate(tmp_path / f"w{s}", GeneratorConfig.preset(
        "tiny", seed=20 + s, agents=1, frames=6))).agents[0], 0, 6, f"agent_{s}") for s in range(8)]
    cfg = SlamConfig().override(FAST)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in seqs], [s.name for s in seqs], cfg, ServerConfig(inter_loops=False))
    team.run(seqs)
    srv = team.server
    tried, passed = 0, []
    for a in range(8):
        for b in range(8):
            if a == b:
                continue
            q, m = team.agents[a].keyframes[-1], team.agents[b].keyframes[(a + b) % len(team.agents[b].keyframes)]
            srv.cloud_tries.clear()
            rec = _record(team, a, q, b, m)
            srv.verify_cloud(rec, a, q, b, m, "sweep")
            tried += 1
            if rec.reason_code in ("unconfirmed", "accepted"):
                passed.append((a, b, rec.render_agree, rec.render_violate))
    assert tried == 56 and passed == [], passed
