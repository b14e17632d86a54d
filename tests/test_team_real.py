"""A two-agent split of a real RGB-D recording: the five Redwood / Augmented ICL-NUIM
living-room-1 frames with noisy depth, cut into agents with DISJOINT frames (agent_0: frames 0-2, agent_1:
frames 3-4). Each agent starts in its own frame (its first camera); the team must accept an inter-agent loop,
bring agent 1 into agent 0's (the global) frame, and track both close to the ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.io.datasets import load_dataset
from swarmsplat.slam.metrics import ate
from swarmsplat.slam.dense.team.server import ServerConfig
from swarmsplat.slam.io.datasets.split import split_sequence
from swarmsplat.slam.run.team import Team

from conftest import shared_data

# Few mapping iterations and every frame a keyframe (2-3 frames per agent): the test is about the split, the
# inter-agent loop and the join, not the map. ~15 s on the shared 2-core machine.
FAST = {
    "mapping": {"iterations": 8, "first_iterations": 25},
    "tracking": {"refine": False},
    "keyframes": {"every": 1},
    "loop_closure": {"min_index_gap": 2},
}
# ATE bound (metres, RMSE after ONE SE(3) alignment of slam.metrics over both agents' frames in the global frame).
# Measured (warp, cpu): 0.15 mm for the team, every frame's error < 0.2 mm. Left in its own frame, agent 1 would
# give 35 mm (frame 3 is 7 cm and 2.2 deg from frame 0). 2 mm leaves >10x headroom and is still 17x below that.
ATE_BOUND_M = 0.002


@pytest.fixture(scope="module")
def real_split():
    from swarmsplat import kernels

    seq = load_dataset(shared_data("redwood_livingroom1_rgbd5")).agents[0]
    ds = split_sequence(seq, [(0, 3), (3, 5)])
    cfg = SlamConfig().override(FAST)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in ds.agents], [s.name for s in ds.agents], cfg, ServerConfig())
    team.run(ds.agents)
    team.finish()
    return seq, ds, team


def test_split_has_disjoint_frames(real_split):
    seq, ds, team = real_split
    assert [len(s) for s in ds.agents] == [3, 2]
    assert not set(ds.agents[0].timestamps) & set(ds.agents[1].timestamps)
    np.testing.assert_array_equal(ds.agents[1].gt_poses, seq.gt_poses[3:5])
    assert team.frames_done == [3, 2]


def test_inter_agent_loop_joins_agent_1(real_split):
    _, _, team = real_split
    srv = team.server
    inter = [r for r in srv.records if r.kind == "inter"]
    accepted = [r for r in inter if r.accepted]
    assert accepted, f"no inter-agent loop accepted: {[r.reason for r in inter]}"
    joins = [r for r in accepted if r.joined]  # the second of two consistent loops joins (server.join_min_loops)
    assert len(joins) == 1 and len(accepted) >= 2
    assert {joins[0].query_agent, joins[0].match_agent} == {"agent_0", "agent_1"}
    assert srv.components() == {0: [0, 1]}  # one global frame, agent 0's
    assert srv.slots[1].component == 0


def test_ate_against_ground_truth(real_split):
    seq, ds, team = real_split
    est = [team.trajectory(a) for a in range(2)]
    assert [len(t) for t, _ in est] == [3, 2]
    t_est = np.concatenate([t for t, _ in est])
    T_est = np.concatenate([T for _, T in est])
    # One alignment for both agents: only right if the join put agent 1 where it belongs in agent 0's frame.
    team_ate = ate(seq.timestamps, seq.gt_poses, t_est, T_est, align="se3")
    assert team_ate.matched == 5
    per_agent = [np.sqrt(np.mean(team_ate.errors[np.isin(team_ate.pairs.timestamps, t)] ** 2)) for t, _ in est]
    print(f"team ATE {1000 * team_ate.rmse:.3f} mm; per agent {[round(1000 * float(e), 3) for e in per_agent]} mm")
    assert team_ate.rmse < ATE_BOUND_M
    assert all(e < ATE_BOUND_M for e in per_agent)
    # Agent 0 alone (3 frames, its own alignment) as well; agent 1's 2 positions cannot fix a rotation alone.
    assert ate(ds.agents[0].timestamps, ds.agents[0].gt_poses, *est[0], align="se3").rmse < ATE_BOUND_M


# ---- two stretches of one real recording, 90 frames apart, as two agents -----------------------------------------

# Redwood 211 frames 0-59 and 150-209: the second stretch stands ~1 m from the first and looks ~55 deg away, yet
# sees 53-78 % of its depth pixels (ground-truth reprojection). The team runs with the default loop closure and
# server (descriptor, candidates, coarse start, join rule); mapping is cut down and the merged-map refinement is
# off, which the join does not depend on. ~40 s on a loaded 2-core machine.
FRAGMENTS = [(0, 60), (150, 210)]
FRAGMENT_SPEEDUP = {"mapping": {"iterations": 10, "first_iterations": 30}, "map_refine": {"iterations_per_keyframe": 0}}
# Team ATE bound (one SE(3) alignment over both agents): measured 0.97 cm with the full defaults; the issue's
# acceptance figure for two real fragments is 0.25 m, and an unjoined or wrongly joined agent 1 is off by ~1 m.
FRAGMENT_ATE_M = 0.03


@pytest.fixture(scope="module")
def fragments():
    from swarmsplat import kernels

    seq = load_dataset(shared_data("redwood_livingroom1_211")).agents[0]
    ds = split_sequence(seq, FRAGMENTS)
    cfg = SlamConfig().override(FRAGMENT_SPEEDUP)
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in ds.agents], [s.name for s in ds.agents], cfg)
    team.run(ds.agents)
    team.finish()
    return seq, team


def test_real_fragments_join_with_the_defaults(fragments):
    _, team = fragments
    srv = team.server
    assert srv.components() == {0: [0, 1]}, [r.reason for r in srv.records if r.kind == "inter"][:6]
    assert srv.joins == 1 and srv.joins_undone == 0
    inter = [r for r in srv.records if r.kind == "inter" and r.source == "descriptor"]
    assert sum(r.accepted for r in inter) >= 0.1 * len(inter)  # the floor: >= 10 % of descriptor candidates


def test_real_fragments_team_ate(fragments):
    seq, team = fragments
    est = [team.trajectory(a) for a in range(2)]
    t_est = np.concatenate([t for t, _ in est])
    T_est = np.concatenate([T for _, T in est])
    team_ate = ate(seq.timestamps, seq.gt_poses, t_est, T_est, align="se3")
    print(f"team ATE {100 * team_ate.rmse:.2f} cm over {team_ate.matched} frames")
    assert team_ate.matched == 120 and team_ate.rmse < FRAGMENT_ATE_M
