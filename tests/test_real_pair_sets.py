"""The measurement helpers behind `perf realpairs` / `perf placerec`: depth co-visibility, rotation angles, the
pair sampler on Redwood, the solved criterion and recall@k on hand-made similarity matrices."""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.perf.place_recognition import recall, revisit_truth
from swarmsplat.perf.redwood_pairs import covisibility, is_solved, rotation_angles, sample_pairs
from swarmsplat.registration.pair import PairResult
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose

from conftest import shared_data

CAM = default_camera(160, 120)


def test_covisibility_of_rendered_views():
    room = TexturedRoom(seed=0)
    T0, T1, T2 = look_pose((0, 0, 0)), look_pose((0.2, 0, 0.1), 10.0), look_pose((0, 0, 0), 180.0)
    d0, d1, d2 = (room.render(T, CAM)[1] for T in (T0, T1, T2))
    same = covisibility(d0, d0, np.eye(4), CAM, stride=4)
    near = covisibility(d0, d1, se3.inverse(T0) @ T1, CAM, stride=4)
    back = covisibility(d0, d2, se3.inverse(T0) @ T2, CAM, stride=4)
    assert same > 0.99 and 0.5 < near < 0.99 and back < 0.02
    # a wrong relative pose makes the depths disagree: low co-visibility even though the views overlap
    assert covisibility(d0, d1, np.eye(4), CAM, stride=4) < near


def test_rotation_angles_and_solved_criterion():
    P = np.stack([look_pose((0, 0, 0)), look_pose((1, 0, 0), 30.0), look_pose((0, 1, 0), -90.0)])
    A = rotation_angles(P)
    assert np.allclose(A, A.T, atol=1e-6) and np.allclose(np.diag(A), 0, atol=1e-5)
    assert abs(A[0, 1] - 30.0) < 1e-6 and abs(A[1, 2] - 120.0) < 1e-6
    T = se3.inverse(P[0]) @ P[1]
    t = T[:3, 3] / np.linalg.norm(T[:3, 3])
    ok = PairResult(T[:3, :3], t, 50, 60, True)
    assert is_solved(ok, T)
    assert not is_solved(PairResult(se3.so3_exp([0, 0.1, 0]) @ T[:3, :3], t, 50, 60, True), T)  # 5.7 deg off
    assert not is_solved(PairResult(T[:3, :3], -t, 50, 60, True), T)
    assert not is_solved(PairResult.failed("no"), T)


def test_recall_at_k_on_a_hand_made_matrix():
    sim = np.array([[1.0, 0.9, 0.2, 0.5],
                    [0.9, 1.0, 0.3, 0.1],
                    [0.2, 0.3, 1.0, 0.05],
                    [0.5, 0.1, 0.05, 1.0]])
    truth = np.zeros((4, 4), bool)
    truth[0, 3] = truth[3, 0] = True  # 0 and 3 revisit each other; 1 and 2 have no revisit
    allowed = ~np.eye(4, dtype=bool)
    r = recall(sim, truth, allowed)
    assert r["queries"] == 2
    assert r["recall@1"] == 0.5  # query 0 ranks 1 first, query 3 ranks 0 first
    assert r["recall@5"] == 1.0
    assert r["sim_true"] == 0.5 and r["sim_other"] == np.percentile(sim[allowed & ~truth], 95)
    P = np.stack([look_pose((0, 0, 0)), look_pose((0.3, 0, 0), 20.0), look_pose((0.3, 0, 0), 40.0)])
    assert revisit_truth(P, P).tolist() == [[True, True, False], [True, True, True], [False, True, True]]


def test_redwood_pair_sampler_is_deterministic_and_in_bins():
    from swarmsplat.perf.redwood_pairs import load_sequence

    seq = load_sequence(shared_data("redwood_livingroom1_211"))
    a = sample_pairs(seq, per_bin=2, seed=0)
    assert a == sample_pairs(seq, per_bin=2, seed=0) and len(a) == 6
    for p in a:
        lo, hi = (float(x) for x in p["bin"].split("-"))
        assert lo <= p["rot_deg"] < hi and p["covis"] >= 0.3 and p["i"] != p["j"]
