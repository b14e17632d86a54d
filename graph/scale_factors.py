"""Loop closures known up to scale (FLOCC-SLAM §III-C, eqs. 7-8) and the scale smoothing factor.

IS factor. The measured relative pose is split into rotation R̄ and translation t̄ (network unit); a scale variable
s rescales the translation, T̂(s) = [R̄, s t̄] (eq. 7), and the residual is GTSAM's between-factor residual with T̂
as the measurement (eq. 8):

    e = Log( T̂(s)^-1 · T_i^-1 · T_j )                                  6-vector [omega, v]

Jacobians (right perturbations as GTSAM; M = T̂^-1 T_i^-1 T_j, Jr^-1 the inverse right Jacobian of SE(3)):

    H_Ti = -Jr^-1(e) Ad((T_i^-1 T_j)^-1)      H_Tj = Jr^-1(e)      H_s = -Jr^-1(e) Ad(M^-1) [0; R̄ᵀ t̄]

At e = 0 these are the paper's H_Ti = -Adj(inv(T_i^-1 T_j)), H_Tj = I and H_s = [0, -t̄]ᵀ — the last with t̄
expressed in the frame of T_j (R̄ᵀ t̄); the paper writes t̄ for it, equal when R̄ ≈ I. GTSAM 4.3's
BetweenFactorPose3 also uses the exact Jr^-1, so the IS factor with s = 1 is that factor, error and Jacobians.

Two implementations of the same maths:
  * `is_loop_factor` — one `gtsam.CustomFactor` per loop (the paper's way; fine for small graphs, tests, and
    as the reference). Each callback costs a copy of the whole `Values` (pybind11 copies the `const Values&`
    argument), so a graph with thousands of them is slow: see `graph.solvers`.
  * `is_residuals` — all loops at once in NumPy, used by `graph.solvers`' Levenberg–Marquardt.

Bias of eq. 8 and the network-unit residual. With a free s, eq. 8's translation residual t_ij - s t̄ carries the
measurement noise multiplied by s, so least squares prefers small scales: per loop, E[ŝ] ≈ s/(1 + 3σ²/|t|²)
(regression dilution), and jointly the solver also pulls the robots' trajectories together to shorten loop
translations. Measured on synthetic teams (perf/flocc_experiment, README): median ŝ/s = 0.99 at σ = 0.15 m,
0.94 at σ = 0.5 m, from any initial scale. `is_residuals_network` compares in the network's unit instead,
e = Log(T̄^-1 [R_ij, t_ij / s]) with the translation information scaled by s0² (the initial scale): the noise is
then additive (1/s is what is estimated without dilution) and a joint shrink of t_ij and s changes nothing. It
reduces the bias rather than removing it: median ŝ/s 0.965 (eq. 8) vs 1.02 (network unit) at σ = 0.5 m on the
test graph (tests/test_graph_solve.py); the paper's eq. 8 stays the default.

Scale smoothing (SS): ||s_b - s_a||²_{Ω_s} with H = -1, +1 is exactly GTSAM's BetweenFactorDouble with
measurement 0, so the built-in factor is used (`scale_smoothing_factor`).
"""

from __future__ import annotations

import gtsam
import numpy as np

from . import lie


def is_residuals(T_i: np.ndarray, T_j: np.ndarray, s: np.ndarray, R_meas: np.ndarray, t_meas: np.ndarray,
                 jacobians: bool = True):
    """IS residuals (and Jacobians) of L loops at once.

    T_i, T_j: [L, 4, 4] T_world_kf of the two keyframes; s: [L] scales; R_meas: [L, 3, 3]; t_meas: [L, 3]
    (network unit). Returns e [L, 6] and, with `jacobians`, H_i [L, 6, 6], H_j [L, 6, 6], H_s [L, 6].
    """
    T_ij = lie.between(T_i, T_j)
    T_hat = np.zeros_like(T_ij)
    T_hat[:, :3, :3] = R_meas
    T_hat[:, :3, 3] = s[:, None] * t_meas
    T_hat[:, 3, 3] = 1.0
    M = lie.between(T_hat, T_ij)
    e = lie.log(M)
    if not jacobians:
        return e
    Jinv = lie.right_jacobian_inv(e)
    H_j = Jinv
    H_i = -Jinv @ lie.adjoint(lie.inverse(T_ij))
    u = np.zeros((len(s), 6))
    u[:, 3:] = np.einsum("lba,lb->la", R_meas, t_meas)  # R̄ᵀ t̄
    H_s = -np.einsum("lab,lb->la", Jinv @ lie.adjoint(lie.inverse(M)), u)
    return e, H_i, H_j, H_s


def is_residuals_network(T_i: np.ndarray, T_j: np.ndarray, s: np.ndarray, R_meas: np.ndarray,
                         t_meas: np.ndarray, jacobians: bool = True):
    """Network-unit IS residual e = Log(T̄^-1 [R_ij, t_ij / s]) (see the module docstring), same shapes as
    `is_residuals`. With lam = 1/s and D = diag(I, lam I): H_Tj = Jr^-1 D, H_Ti = -Jr^-1 D Ad(T_ij^-1),
    H_s = -Jr^-1 [0; R_ijᵀ t_ij] / s²."""
    T_ij = lie.between(T_i, T_j)
    lam = 1.0 / s
    A = T_ij.copy()
    A[:, :3, 3] *= lam[:, None]
    T_meas = np.zeros_like(T_ij)
    T_meas[:, :3, :3] = R_meas
    T_meas[:, :3, 3] = t_meas
    T_meas[:, 3, 3] = 1.0
    e = lie.log(lie.between(T_meas, A))
    if not jacobians:
        return e
    Jinv = lie.right_jacobian_inv(e)
    JD = Jinv.copy()
    JD[:, :, 3:] *= lam[:, None, None]
    H_j = JD
    H_i = -JD @ lie.adjoint(lie.inverse(T_ij))
    u = np.einsum("lba,lb->la", T_ij[:, :3, :3], T_ij[:, :3, 3])  # R_ijᵀ t_ij
    H_s = -np.einsum("lab,lb->la", Jinv[:, :, 3:], u) / (s**2)[:, None]
    return e, H_i, H_j, H_s


def is_loop_factor(key_i: int, key_j: int, key_s: int, T_meas: np.ndarray,
                   noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """The IS loop factor as one gtsam.CustomFactor on (Pose3 key_i, Pose3 key_j, double key_s).

    T_meas: [4, 4] measured relative pose with translation in the network unit. Computed with GTSAM's own Pose3
    maps (an implementation independent of `is_residuals`, which the tests compare it with).
    """
    R_meas = gtsam.Rot3(np.asarray(T_meas[:3, :3], float))
    t_meas = np.asarray(T_meas[:3, 3], float).copy()
    u = np.concatenate([np.zeros(3), R_meas.matrix().T @ t_meas])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None):
        Ti, Tj, s = values.atPose3(key_i), values.atPose3(key_j), values.atDouble(key_s)
        T_ij = Ti.between(Tj)
        M = gtsam.Pose3(R_meas, s * t_meas).between(T_ij)
        e = gtsam.Pose3.Logmap(M)
        if H is not None:
            Jinv = gtsam.Pose3.LogmapDerivative(e)
            H[0] = -Jinv @ T_ij.inverse().AdjointMap()
            H[1] = Jinv
            H[2] = (-Jinv @ M.inverse().AdjointMap() @ u).reshape(6, 1)
        return e

    return gtsam.CustomFactor(noise, gtsam.KeyVector([key_i, key_j, key_s]), error)


def scale_smoothing_factor(key_a: int, key_b: int, sigma: float) -> gtsam.NonlinearFactor:
    """SS tie between two loop scales: 0.5 (s_b - s_a)² / sigma² (BetweenFactorDouble, measurement 0)."""
    return gtsam.BetweenFactorDouble(key_a, key_b, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma))


def scale_smoothing_custom_factor(key_a: int, key_b: int, sigma: float) -> gtsam.CustomFactor:
    """The same tie written as the paper gives it (residual s_b - s_a, H = -1, +1), as a CustomFactor; kept to
    show it equals `scale_smoothing_factor` (tests), not used by the solvers."""

    def error(this, values, H):
        if H is not None:
            H[0] = -np.ones((1, 1))
            H[1] = np.ones((1, 1))
        return np.array([values.atDouble(key_b) - values.atDouble(key_a)])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), gtsam.KeyVector([key_a, key_b]), error)
