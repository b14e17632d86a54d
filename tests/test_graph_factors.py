"""graph/: batched Lie maps, the IS and smoothing factors' Jacobians, confidence (eqs. 1-2)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from swarmsplat.graph import lie
from swarmsplat.graph.confidence import correspondence_ratio, loop_confidence, scale_information
from swarmsplat.graph.scale_factors import (
    is_loop_factor, is_residuals, scale_smoothing_custom_factor, scale_smoothing_factor)
from swarmsplat.kernels.errors import InputError


def _random_poses(rng, n, scale=1.0):
    return np.stack([gtsam.Pose3.Expmap(rng.normal(size=6) * scale).matrix() for _ in range(n)])


def test_lie_maps_match_gtsam():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(60, 6)) * np.repeat([1.0, 1e-3, 1e-7], 20)[:, None]
    xi[0, :3] = [0.0, 0.0, np.pi - 1e-5]  # near the cut locus of log
    T = np.stack([gtsam.Pose3.Expmap(x).matrix() for x in xi])
    assert np.allclose(lie.exp(xi), T, atol=1e-12)
    logs = np.stack([gtsam.Pose3.Logmap(gtsam.Pose3(t)) for t in T])
    assert np.allclose(lie.log(T), logs, atol=1e-9)
    jr = np.stack([gtsam.Pose3.LogmapDerivative(x) for x in logs])
    assert np.allclose(lie.right_jacobian_inv(logs), jr, atol=1e-9)
    ad = np.stack([gtsam.Pose3(t).AdjointMap() for t in T])
    assert np.allclose(lie.adjoint(T), ad, atol=1e-12)


def _values(Ti, Tj, s):
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(Ti))
    v.insert(2, gtsam.Pose3(Tj))
    v.insert(3, float(s))
    return v


def _numerical_jacobian(factor, v, h=1e-6):
    """Central differences of the unwhitened error over (Pose3 1, Pose3 2, double 3), right perturbations."""
    J = np.zeros((6, 13))
    for k in range(13):
        d = np.zeros(13)
        d[k] = h
        out = []
        for sign in (1, -1):
            w = gtsam.Values(v)
            w.update(1, v.atPose3(1).retract(sign * d[:6]))
            w.update(2, v.atPose3(2).retract(sign * d[6:12]))
            w.update(3, v.atDouble(3) + sign * d[12])
            out.append(factor.unwhitenedError(w))
        J[:, k] = (out[0] - out[1]) / (2 * h)
    return J


def test_is_factor_jacobians_match_numerical_and_batched():
    rng = np.random.default_rng(1)
    L = 6
    Ti, Tj, Tm = _random_poses(rng, L), _random_poses(rng, L), _random_poses(rng, L)
    s = rng.uniform(0.3, 3.0, L)
    e, Hi, Hj, Hs = is_residuals(Ti, Tj, s, Tm[:, :3, :3], Tm[:, :3, 3])
    for n in range(L):
        f = is_loop_factor(1, 2, 3, Tm[n], gtsam.noiseModel.Unit.Create(6))
        v = _values(Ti[n], Tj[n], s[n])
        A, b = f.linearize(v).jacobian()
        assert np.allclose(A, _numerical_jacobian(f, v), atol=1e-7)  # analytic == central differences
        assert np.allclose(-b, e[n], atol=1e-12)  # CustomFactor == batched NumPy, error ...
        assert np.allclose(A, np.column_stack([Hi[n], Hj[n], Hs[n]]), atol=1e-12)  # ... and Jacobians


def test_is_jacobians_reduce_to_the_papers_at_zero_error():
    rng = np.random.default_rng(2)
    Ti = _random_poses(rng, 1)
    Tm = _random_poses(rng, 1)
    s = np.array([1.7])
    That = Tm.copy()
    That[0, :3, 3] *= s[0]
    Tj = Ti @ That  # the loop is satisfied exactly
    e, Hi, Hj, Hs = is_residuals(Ti, Tj, s, Tm[:, :3, :3], Tm[:, :3, 3])
    assert np.allclose(e, 0, atol=1e-12)
    Tij = lie.between(Ti, Tj)
    assert np.allclose(Hi[0], -lie.adjoint(lie.inverse(Tij))[0], atol=1e-12)  # -Adj(inv(Ti^-1 Tj))
    assert np.allclose(Hj[0], np.eye(6), atol=1e-12)  # I
    assert np.allclose(Hs[0], np.r_[np.zeros(3), -Tm[0, :3, :3].T @ Tm[0, :3, 3]], atol=1e-12)  # [0, -t̄] in T_j


def test_is_factor_with_unit_scale_is_between_factor():
    rng = np.random.default_rng(3)
    for _ in range(4):
        Ti, Tj, Tm = _random_poses(rng, 3)
        noise = gtsam.noiseModel.Gaussian.Information(np.diag(rng.uniform(1, 50, 6)))
        v = _values(Ti, Tj, 1.0)
        f_is = is_loop_factor(1, 2, 3, Tm, noise)
        f_b = gtsam.BetweenFactorPose3(1, 2, gtsam.Pose3(Tm), noise)
        assert f_is.error(v) == pytest.approx(f_b.error(v), rel=1e-12)
        A_is, b_is = f_is.linearize(v).jacobian()
        A_b, b_b = f_b.linearize(v).jacobian()
        assert np.allclose(A_is[:, :12], A_b, atol=1e-9)
        assert np.allclose(b_is, b_b, atol=1e-12)


def test_scale_smoothing_factor_is_the_papers():
    v = gtsam.Values()
    v.insert(10, 0.8)
    v.insert(11, 1.3)
    built_in, custom = scale_smoothing_factor(10, 11, 0.1), scale_smoothing_custom_factor(10, 11, 0.1)
    assert built_in.error(v) == pytest.approx(0.5 * (1.3 - 0.8) ** 2 / 0.01, rel=1e-12)
    assert custom.error(v) == pytest.approx(built_in.error(v), rel=1e-12)
    A_c, b_c = custom.linearize(v).jacobian()
    A_b, b_b = built_in.linearize(v).jacobian()
    assert np.allclose(A_c, [[-10.0, 10.0]]) and np.allclose(A_c, A_b) and np.allclose(b_c, b_b)


def test_confidence():
    assert correspondence_ratio(150, 300) == 0.5
    assert loop_confidence(0.29) is None  # below R_thr = 0.3
    assert loop_confidence(1.0) == pytest.approx(0.5)
    p_lo, p_hi = loop_confidence(0.5, k=5), loop_confidence(1.5, k=5)
    assert p_lo == pytest.approx(1 / (1 + np.exp(2.5))) and p_hi == pytest.approx(1 / (1 + np.exp(-2.5)))
    assert loop_confidence(0.5, k=20) < p_lo  # steeper logistic
    assert loop_confidence(0.5, r_thr=0.6) is None
    assert np.allclose(scale_information(np.eye(6) * 4, 0.25), np.eye(6))
    with pytest.raises(InputError):
        correspondence_ratio(10, 0)
    with pytest.raises(InputError):
        scale_information(np.eye(6), 0.0)
    with pytest.raises(InputError):
        loop_confidence(float("nan"))


def test_network_unit_residual_jacobians_match_numerical():
    from swarmsplat.graph.scale_factors import is_residuals_network

    rng = np.random.default_rng(4)
    L = 5
    Ti, Tj, Tm = _random_poses(rng, L), _random_poses(rng, L), _random_poses(rng, L)
    s = rng.uniform(0.4, 2.5, L)
    e, Hi, Hj, Hs = is_residuals_network(Ti, Tj, s, Tm[:, :3, :3], Tm[:, :3, 3])

    def f(a, b, c):
        return is_residuals_network(a, b, c, Tm[:, :3, :3], Tm[:, :3, 3], jacobians=False)

    h = 1e-6
    for k in range(6):
        d = np.zeros((L, 6))
        d[:, k] = h
        num_i = (f(Ti @ lie.exp(d), Tj, s) - f(Ti @ lie.exp(-d), Tj, s)) / (2 * h)
        num_j = (f(Ti, Tj @ lie.exp(d), s) - f(Ti, Tj @ lie.exp(-d), s)) / (2 * h)
        assert np.allclose(num_i, Hi[:, :, k], rtol=1e-6, atol=1e-6)
        assert np.allclose(num_j, Hj[:, :, k], rtol=1e-6, atol=1e-6)
    assert np.allclose((f(Ti, Tj, s + h) - f(Ti, Tj, s - h)) / (2 * h), Hs, rtol=1e-6, atol=1e-6)
    # the measurement reproduced exactly (t_ij = s t̄) gives zero residual
    That = Tm.copy()
    That[:, :3, 3] *= s[:, None]
    assert np.allclose(f(Ti, Ti @ That, s), 0.0, atol=1e-12)
