"""Loop closure that never makes a trajectory worse: rigid submap frames under repeated moves, edge information
from the measurements, inconsistent loops rejected after optimisation, unjustified moves not applied, pose-based
candidates by view overlap."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.loops.edge_information import (
    InformationModel, OdometryChain, information, registration_covariance)
from swarmsplat.slam.dense.frames import make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.loops.loop_closure import Edge, LoopCandidate, LoopCloser
from swarmsplat.slam.dense.loops.view_overlap import view_overlap
from swarmsplat.slam.dense.submaps import Keyframe, world_pose

import slam_scene


def test_repeated_submap_moves_keep_the_frame_rigid():
    """The Redwood failure: a submap frame a hair off SE(3), moved again and again with transpose-inverses, grew a
    scale error that doubled with every optimisation. Every stored frame is now projected back onto SE(3)."""
    rng = np.random.default_rng(0)
    gm = GaussianMap()
    s = gm.new_submap(se3.exp(rng.normal(size=6)) + 1e-6 * rng.normal(size=(4, 4)))
    assert se3.rigidity_error(s.T_world_local) < 1e-12
    for _ in range(60):
        D = se3.exp(0.01 * rng.normal(size=6))
        D[:3, :3] *= 1 + 1e-7  # a slightly non-rigid move, as composed poses are
        gm.transform_submap(s, D)
        T_target = s.T_world_local @ se3.exp(0.01 * rng.normal(size=6))
        gm.place_submap(s, T_target)
    assert se3.rigidity_error(s.T_world_local) < 1e-12
    P = se3.project_rigid(np.diag([2.0, 2.0, 2.0, 1.0]) @ se3.exp(rng.normal(size=6)))
    assert se3.rigidity_error(P) < 1e-12 and np.linalg.det(P[:3, :3]) > 0


def test_registration_information_is_transported_to_the_source_frame():
    rng = np.random.default_rng(1)
    model = InformationModel(sigma_floor_rot=1e-9, sigma_floor_trans=1e-9)
    q = rng.normal(size=(500, 3)) + np.array([0, 0, 2.0])
    H = np.zeros((6, 6))
    for p in q:
        G = np.hstack([-se3.hat(p), np.eye(3)])
        H += G.T @ G
    T = se3.exp(np.array([0.1, -0.2, 0.05, 0.3, 0.1, -0.2]))
    cov = registration_covariance(H, len(q), 0.01, T, model)
    I_t = H / len(q) * model.n_eff / 0.01 ** 2
    A = se3.adjoint(T)
    want = A.T @ I_t @ A
    np.testing.assert_allclose(np.linalg.inv(cov), want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    # a floor raises every standard deviation to at least its value
    floored = registration_covariance(H, len(q), 0.01, T, InformationModel(sigma_floor_rot=0.01, sigma_floor_trans=0.05))
    assert np.all(np.sqrt(np.diag(floored))[3:] >= 0.05 - 1e-12)
    I = information(floored, InformationModel(sigma_floor_rot=0.01, sigma_floor_trans=0.05))
    assert np.all(np.linalg.eigvalsh(I) > 0)


def test_odometry_chain_covariance_matches_monte_carlo():
    rng = np.random.default_rng(2)
    model = InformationModel(sigma_floor_rot=1e-9, sigma_floor_trans=1e-9)
    steps = [se3.exp(np.array([0.02, 0.1, -0.05, 0.2, 0.0, 0.1])), se3.exp(np.array([-0.1, 0.05, 0.0, 0.0, 0.3, 0.1]))]
    covs = [np.diag([1e-4, 4e-4, 1e-4, 1e-3, 4e-4, 9e-4]), np.diag([4e-4, 1e-4, 1e-4, 4e-4, 1e-3, 1e-4])]
    chain = OdometryChain(model)
    for T, C in zip(steps, covs):
        chain.add(T, C)
    T_true = steps[0] @ steps[1]
    errs = []
    for _ in range(4000):
        Ts = [T @ se3.exp(rng.multivariate_normal(np.zeros(6), C)) for T, C in zip(steps, covs)]
        errs.append(se3.log(se3.inverse(T_true) @ Ts[0] @ Ts[1]))
    mc = np.cov(np.array(errs).T)
    np.testing.assert_allclose(chain.cov, mc, atol=1.5e-4, rtol=0.12)


def _chain(n: int, cam, drift_per_step: np.ndarray):
    """n keyframes in n submaps on a short arc; the estimated submap frames carry a growing drift."""
    a = np.radians(np.linspace(0, 12, n))
    true = [se3.make(se3.so3_exp(np.array([0.0, ai, 0.0])), np.array([0.4 * np.sin(ai), 0.0, 0.0])) for ai in a]
    cfg = SlamConfig().override({"loop_closure": {"min_index_gap": 3, "tau_sim": 0.5}}).loop_closure
    gm, kfs, closer = GaussianMap(), [], LoopCloser(cfg)
    drift = np.eye(4)
    for k, T in enumerate(true):
        s = gm.new_submap(drift @ T)
        rgbd = make_rgbd(*slam_scene.render(T, cam), cam, min_depth=0.1, max_depth=10.0)
        kf = Keyframe(k, 10 * k, float(k), s.id, np.eye(4), None, rgbd)
        s.keyframe_ids.append(k)
        kfs.append(kf)
        closer.add_keyframe(kf, kfs, gm)
        drift = se3.exp(drift_per_step) @ drift
    return true, gm, kfs, closer


def _add_loop(closer: LoopCloser, kfs, i: int, j: int, T_ij: np.ndarray, info: float = 1e4) -> LoopCandidate:
    c = LoopCandidate(j, i, kfs[j].frame_index, kfs[i].frame_index, 1.0, accepted=True, reason="accepted")
    closer.log.append(c)
    closer.loops.append(Edge(i, j, T_ij, np.diag([info] * 6), c))
    return c


def test_inconsistent_loop_is_rejected_and_the_graph_solved_again():
    cam = slam_scene.camera(40, 30)
    true, gm, kfs, closer = _chain(6, cam, np.array([0.0, 0.002, 0.0, 0.004, 0.0, 0.002]))
    good = _add_loop(closer, kfs, 0, 5, se3.inverse(true[0]) @ true[5])
    bad = _add_loop(closer, kfs, 1, 4, se3.inverse(true[1]) @ true[4] @ se3.exp(np.array([0, 0, 0.2, 0.4, 0, 0])))
    out = closer.optimise(kfs, gm)
    assert out["applied"] and out["rejected"] == 1
    assert good.accepted and not bad.accepted and bad.reason.startswith("inconsistent after optimisation")
    err = np.linalg.norm(world_pose(gm, kfs[5])[:3, 3] - true[5][:3, 3])
    assert err < 0.01, err


def test_optimisation_that_moves_further_than_the_loops_justify_is_not_applied():
    """Odometry that disagrees with the current poses (a corrupted state, as the non-rigid submap frames of the
    Redwood failure were) would move keyframes far while the loop agrees with them: the move is not applied and
    the new loop is rejected with the reason."""
    cam = slam_scene.camera(40, 30)
    true, gm, kfs, closer = _chain(6, cam, np.zeros(6))
    for e in closer.odometry:  # each odometry edge now claims 5 cm more forward motion
        e.T_ij = e.T_ij @ se3.exp(np.array([0, 0, 0, 0, 0, 0.05]))
    c = _add_loop(closer, kfs, 3, 5, se3.inverse(world_pose(gm, kfs[3])) @ world_pose(gm, kfs[5]), info=1e8)
    before = [world_pose(gm, k).copy() for k in kfs]
    with pytest.warns(RuntimeWarning, match="not applied"):
        out = closer.optimise(kfs, gm)
    assert not out["applied"] and closer.not_applied == 1
    assert not c.accepted and "more than the loops justify" in c.reason
    for k, T in zip(kfs, before):
        np.testing.assert_allclose(world_pose(gm, k), T, atol=1e-12)


def test_view_overlap_of_tracked_poses():
    cam = slam_scene.camera(80, 60)
    T0 = np.eye(4)
    f0 = make_rgbd(*slam_scene.render(T0, cam), cam, min_depth=0.1, max_depth=10.0)
    T1 = se3.exp(np.array([0.0, 0.05, 0.0, 0.05, 0.0, 0.0]))
    f1 = make_rgbd(*slam_scene.render(T1, cam), cam, min_depth=0.1, max_depth=10.0)
    assert view_overlap(f0, f0, np.eye(4)) > 0.95
    assert view_overlap(f1, f0, se3.inverse(T0) @ T1) > 0.7
    turned = se3.make(se3.so3_exp(np.array([0.0, np.pi, 0.0])), np.zeros(3))  # looking the other way
    assert view_overlap(f1, f0, turned) < 0.05


@pytest.mark.parametrize("fallback", [False, True])
def test_a_failing_candidate_restarts_from_fpfh_only_when_asked(monkeypatch, fallback):
    """loop_closure.global_fallback: a candidate that fails from the tracked pose is rejected (false, the default)
    or restarted from FPFH + RANSAC (true); the restart is what costs seconds without a similarity gate."""
    from swarmsplat.registration import rgbd as rgbd_mod
    from swarmsplat.registration.result import RegistrationResult

    calls = []

    def fake_global(*args, **kwargs):
        calls.append(1)
        return RegistrationResult.failure(np.eye(4), "too few points", "fpfh_ransac")

    monkeypatch.setattr(rgbd_mod, "global_registration", fake_global)
    cam = slam_scene.camera(40, 30)
    _, gm, kfs, closer = _chain(6, cam, np.zeros(6))
    closer.cfg = closer.cfg.model_copy(update={"global_fallback": fallback})
    gm.place_submap(gm.submaps[0], gm.submaps[0].T_world_local @ se3.exp(np.array([0, 0, 0, 0.5, 0.3, 0.0])))
    c = closer.verify(LoopCandidate(5, 0, kfs[5].frame_index, kfs[0].frame_index, 1.0), kfs, gm)  # 58 cm off
    assert not c.accepted and len(calls) == int(fallback)
