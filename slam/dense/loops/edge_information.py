"""Pose-graph edge information from the measurements (GRAND-SLAM eqs. 10–11) instead of fixed sigmas.

A registration reports Open3D's information matrix H = Σ GᵀG over its K correspondences (G = [-[q]x, I] at the
target point q, twist [ω, v] of a *left* perturbation in the target frame; registration.result). As an inverse
covariance it is H / σ² for independent residuals of std σ — wildly over-confident for dense RGB-D, whose
residuals are strongly correlated (one depth bias moves thousands of pixels together). We therefore read it as

    I_target = (H / K) · n_eff / σ²,   σ = max(inlier RMSE, rmse_floor)

so the *shape* of H (which directions the geometry constrains: a corridor leaves one translation free) and the
registration's own error level set the information, while `n_eff` — the number of effectively independent
residuals — sets its overall confidence, the same for tracking and loop edges. GTSAM's BetweenFactorPose3 measures
its error in the tangent space of the source (j) frame, so the matrix is transported there with the adjoint:
I_j = Ad(T)ᵀ I_target Ad(T) for T = T_target_source. Each edge's standard deviations are finally clamped below by
`sigma_floor_*` (no edge is trusted more than that).

A keyframe-to-keyframe tracking edge chains several frame-to-frame steps; `OdometryChain` adds their covariances
(each moved into the newest frame with the adjoint), as a chain of independent relative measurements does.

A loop registered between two *windows* of keyframes fused into clouds (the cloud route) is only as consistent as
the poses that fused them: `window_covariance` is the tracking chain's covariance from a window's centre to its
members, averaged over them, and a cloud loop's covariance adds both windows' to the registration's (its ICP
cannot see that part: the clouds it aligns already carry it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels import se3


@dataclass(frozen=True)
class InformationModel:
    n_eff: float = 25.0  # effectively independent residuals per registration
    rmse_floor: float = 0.002  # m: below this a registration's RMSE says more about resolution than accuracy
    sigma_floor_rot: float = 2e-4  # rad
    sigma_floor_trans: float = 5e-4  # m
    failed_sigma_rot: float = 0.05  # rad: a tracking step that fell back to constant velocity
    failed_sigma_trans: float = 0.1  # m


def fixed_information(sigma_rot: float, sigma_trans: float) -> np.ndarray:
    """diag(1/σ²) in twist order [ω, v]."""
    return np.diag([sigma_rot ** -2] * 3 + [sigma_trans ** -2] * 3)


def _clamp(cov: np.ndarray, model: InformationModel) -> np.ndarray:
    """Symmetrise and raise the covariance to at least the floor sigmas (in the metric diag(σ_floor))."""
    cov = 0.5 * (cov + cov.T)
    s = np.array([model.sigma_floor_rot] * 3 + [model.sigma_floor_trans] * 3)
    C = cov / np.outer(s, s)  # floor sigmas -> unit
    w, V = np.linalg.eigh(C)
    C = (V * np.maximum(w, 1.0)) @ V.T
    return C * np.outer(s, s)


def registration_covariance(H: np.ndarray, n_corr: int, rmse: float, T_target_source: np.ndarray,
                            model: InformationModel) -> np.ndarray:
    """6x6 covariance of a registration result in the source frame's tangent space (module docstring)."""
    H = np.asarray(H, dtype=np.float64)
    if n_corr <= 0 or not np.all(np.isfinite(H)):
        return failed_covariance(model)
    sigma = max(float(rmse) if np.isfinite(rmse) else 0.0, model.rmse_floor)
    I_t = (H / n_corr) * model.n_eff / sigma ** 2
    A = se3.adjoint(T_target_source)
    I_s = A.T @ I_t @ A
    # Directions H does not constrain at all (pure degeneracy) get a large but finite variance.
    w, V = np.linalg.eigh(0.5 * (I_s + I_s.T))
    w = np.maximum(w, 1e-6 * max(float(w.max()), 1e-12))
    return _clamp((V / w) @ V.T, model)


def failed_covariance(model: InformationModel) -> np.ndarray:
    return np.diag([model.failed_sigma_rot ** 2] * 3 + [model.failed_sigma_trans ** 2] * 3)


def information(cov: np.ndarray, model: InformationModel) -> np.ndarray:
    """The information matrix of a covariance, after the floor (symmetric positive definite)."""
    cov = _clamp(np.asarray(cov, dtype=np.float64), model)
    out = np.linalg.inv(cov)
    return 0.5 * (out + out.T)


def window_covariance(step_cov: dict[int, np.ndarray], center: int, members) -> np.ndarray:
    """Mean over `members` (keyframe ids) of the tracking chain's covariance between keyframe `center` and each:
    the sum of the steps' covariances `step_cov[k]` (edge k -> k+1) in between. Steps are summed without moving
    them between frames (windows span a few keyframes, whose relative rotations are small); a step without a
    covariance counts as zero."""
    out = np.zeros((6, 6))
    members = list(members)
    for m in members:
        for k in range(min(center, m), max(center, m)):
            c = step_cov.get(k)
            if c is not None:
                out = out + c
    return out / max(len(members), 1)


def step_covariances(odometry) -> dict[int, np.ndarray]:
    """{i: covariance} of an agent's tracking edges i -> i + 1 (slam.dense.loops.loop_closure.Edge, `info`)."""
    return {e.i: np.linalg.inv(e.info) for e in odometry if e.j == e.i + 1}


@dataclass
class OdometryChain:
    """Covariance of the relative pose from the last keyframe to the newest frame, step by step."""

    model: InformationModel
    cov: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    steps: int = 0

    def add(self, T_prev_cur: np.ndarray, cov_step: np.ndarray) -> None:
        """One tracking step (pose of the new frame in the previous one, its covariance in the new frame)."""
        A = se3.adjoint(se3.inverse(T_prev_cur))  # tangent at the previous frame -> tangent at the new one
        self.cov = A @ self.cov @ A.T + cov_step
        self.steps += 1

    def reset(self) -> None:
        self.cov, self.steps = np.zeros((6, 6)), 0

    def information(self) -> np.ndarray:
        return information(self.cov if self.steps else failed_covariance(self.model), self.model)
