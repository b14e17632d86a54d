"""The cloud route is a fallback (slam.dense.loops.loop_closure.LoopCloser.detect, and between agents in one frame
slam.dense.team.cloud_route.CloudRoute.cloud_allowed): a keyframe whose revisit keyframe registration closes
takes no cloud route; one whose candidates all fail the gates takes it for the best ones, within its budget. A
cloud loop carries the tracking spread of its two windows (slam.dense.loops.edge_information.window_covariance).
"""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.loops import loop_closure as lc_mod
from swarmsplat.slam.dense.loops.edge_information import step_covariances, window_covariance
from swarmsplat.slam.dense.loops.loop_closure import Edge, LoopCloser
from swarmsplat.slam.dense.submaps import Keyframe

import slam_scene


def test_window_covariance_is_the_mean_chain_to_the_members():
    steps = {k: np.eye(6) * (k + 1) for k in range(6)}  # edge k -> k+1 has covariance (k+1) I
    # centre 3, members 1, 3, 5: chains 1->3 = 2+3, 3->3 = 0, 3->5 = 4+5 -> mean (5 + 0 + 9) / 3
    assert np.allclose(window_covariance(steps, 3, [1, 3, 5]), np.eye(6) * 14 / 3)
    assert np.allclose(window_covariance(steps, 3, [3]), 0)
    assert np.allclose(window_covariance({}, 3, [0, 6]), 0)  # no tracking covariances: nothing added
    edges = [Edge(0, 1, np.eye(4), np.eye(6) * 4.0), Edge(1, 2, np.eye(4), np.eye(6) * 2.0),
             Edge(0, 2, np.eye(4), np.eye(6))]  # a loop (0 -> 2) is not a step
    cov = step_covariances(edges)
    assert sorted(cov) == [0, 1] and np.allclose(cov[0], np.eye(6) / 4) and np.allclose(cov[1], np.eye(6) / 2)


class _Reg:
    def __init__(self, ok: bool):
        self.success, self.fitness, self.inlier_rmse = ok, (0.9 if ok else 0.1), (0.01 if ok else 0.05)
        self.T_target_source, self.reason = np.eye(4), "" if ok else "poor alignment"
        self.information, self.n_correspondences = np.eye(6) * 1e4, 500


@pytest.fixture
def revisit():
    """Six keyframes of the analytic scene, the last back where the first two were; a closer with the cloud route
    on whose candidates are keyframes 0 and 1 (descriptors all alike)."""
    cam = slam_scene.camera(80, 60)
    cfg = SlamConfig().override({"loop_closure": {"min_index_gap": 3, "cloud_route": True, "cloud_per_keyframe": 1,
                                                  "candidates": "descriptor", "top_k": 2,
                                                  "descriptor": "thumbnail"}}).loop_closure
    a = np.radians(np.array([0, 6, 12, 12, 6, 1.0]))
    gm, kfs, closer = GaussianMap(), [], LoopCloser(cfg)
    for k, ai in enumerate(a):
        T = se3.make(se3.so3_exp(np.array([0.0, ai, 0.0])), np.array([0.4 * np.sin(ai), 0.0, 0.0]))
        s = gm.new_submap(T)
        kf = Keyframe(k, 10 * k, float(k), s.id, np.eye(4), None, make_rgbd(*slam_scene.render(T, cam), cam,
                                                                            min_depth=0.1, max_depth=10.0))
        s.keyframe_ids.append(k)
        kfs.append(kf)
        closer.add_keyframe(kf, kfs, gm)
        kf.descriptor = np.ones(4) / 2.0
    return closer, kfs, gm


def _run(revisit, monkeypatch, passes: set[int]):
    closer, kfs, gm = revisit
    monkeypatch.setattr(lc_mod, "register_loop", lambda q, j, *a, **k: _Reg(
        next(i for i, o in enumerate(kfs) if o.small is j) in passes))
    clouds = []

    def fake_cloud(c, q, j, keyframes, gmap, T_init, *, logged=False):
        clouds.append((c.match_kf, logged))
        closer.cloud_tries[q.id] = closer.cloud_tries.get(q.id, 0) + 1
        c.route, c.reason = "cloud", "render check: test"
        return c

    monkeypatch.setattr(closer, "_verify_cloud", fake_cloud)
    accepted = closer.detect(kfs[5], kfs, gm)
    return closer, accepted, clouds


def test_a_revisit_the_images_close_takes_no_cloud_route(revisit, monkeypatch):
    closer, accepted, clouds = _run(revisit, monkeypatch, passes={1})
    assert [c.match_kf for c in accepted] == [1] and clouds == []
    assert len(closer.log) == 2 and closer.log[0].reason.startswith("fitness")  # keyframe 0 failed the gates


def test_a_revisit_nothing_closes_takes_the_route_within_its_budget(revisit, monkeypatch):
    closer, accepted, clouds = _run(revisit, monkeypatch, passes=set())
    assert accepted == [] and len(clouds) == 1 and clouds[0][1] is True  # budget 1; already logged
    assert len(closer.log) == 2 and len({id(c) for c in closer.log}) == 2  # each candidate logged once
    assert sorted(c.route for c in closer.log) == ["cloud", "image"]


def test_a_join_takes_the_stricter_free_space_gate():
    """A pose found without a start (a join) may align a repeated place: its render check allows less of the map in
    front of the observed surface than a loop from the tracked pose does (decision 0012)."""
    from swarmsplat.slam.dense.loops.render_check import RenderScore
    from swarmsplat.slam.dense.team.cloud_route import render_gate

    cfg = SlamConfig()
    lc, join = cfg.loop_closure, cfg.server.join_max_violate
    assert join < lc.render_max_violate
    assert render_gate(lc).max_violate == lc.render_max_violate and render_gate(lc, join).max_violate == join
    s = RenderScore(pixels=1000, covisible=0.6, agree=0.7, violate=(join + lc.render_max_violate) / 2,
                    photometric=0.05)
    assert render_gate(lc).verdict(s) == "" and "in front" in render_gate(lc, join).verdict(s)
    assert render_gate(lc, 0.5).max_violate == lc.render_max_violate  # never looser than the loop gate
