"""Regression on real data: 211 frames of the ICL-NUIM living room (../shared/data/redwood_livingroom1_211).

With the default loop closure this sequence used to come out at 51.8 cm ATE (1.02 cm without loop closure): every
optimisation re-placed submap frames that had drifted off SE(3), and the transpose-inverse of a non-rigid frame
doubled its scale error each time. Mapping is switched off here (tracking is frame-to-frame and loop closure uses
the keyframes' RGB-D, so neither reads the map), which keeps the test at about a minute.
"""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3


@pytest.fixture(scope="module")
def redwood_run():
    import torch

    from swarmsplat import kernels
    from conftest import shared_data
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_sequence

    path = shared_data("redwood_livingroom1_211")
    kernels.use("warp", "cpu")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    cfg = SlamConfig().override({"mapping": {"iterations": 0, "first_iterations": 0},
                                 "tracking": {"refine": False, "refine_on_coarse_failure": False}})
    seq = load_sequence(path)
    agent = Agent(seq.camera, cfg, name="redwood")
    for i in range(len(seq)):
        f = seq[i]
        agent.step(f.index, f.timestamp, f.color, f.depth)
    torch.set_num_threads(n)
    return seq, agent


def _ate(seq, stamps, T):
    from swarmsplat.slam.metrics import ate

    return ate(seq.timestamps, seq.gt_poses, stamps, T, align="se3", max_diff=1e-3).rmse


def test_loop_closure_does_not_wreck_the_trajectory(redwood_run):
    seq, agent = redwood_run
    stamps, T = agent.trajectory(per_keyframe=True)
    _, T0 = agent.trajectory_no_lc()
    with_lc, without = _ate(seq, stamps, T), _ate(seq, stamps, T0)
    assert len(T) == len(seq) == 211
    assert with_lc < 0.015, (with_lc, without)  # was 0.518
    # The reference is a pseudo ground truth (see its PROVENANCE); 2 mm is its stated accuracy.
    assert with_lc <= without + 0.002, (with_lc, without)
    assert max(se3.rigidity_error(s.T_world_local) for s in agent.gmap.submaps) < 1e-9
    assert agent.loops.not_applied == 0


def test_the_revisit_is_closed_and_every_loop_fits_the_optimum(redwood_run):
    from swarmsplat.slam.dense.loops.loop_check import loop_residuals
    from swarmsplat.slam.dense.submaps import world_pose

    seq, agent = redwood_run
    acc = [c for c in agent.loops.log if c.accepted]
    assert any(c.query_frame >= 170 and c.match_frame <= 25 for c in acc), "the return to the start is not closed"
    assert {c.source for c in agent.loops.log} == {"descriptor", "pose"}
    poses = {k.id: world_pose(agent.gmap, k) for k in agent.keyframes}
    cfg = agent.cfg.loop_closure
    for r in loop_residuals(poses, [(e.i, e.j, e.T_ij) for e in agent.loops.active_loops]):
        assert r.trans_m < 2 * cfg.residual_max_trans and r.rot_deg < 2 * cfg.residual_max_deg, r
