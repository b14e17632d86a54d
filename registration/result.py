"""The outcome of a registration: a pose, whether to trust it, and why not when not."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

OK = "ok"
TOO_FEW_POINTS = "too few points"
DEGENERATE = "degenerate geometry"
NOT_CONVERGED = "not converged"
INVALID_INPUT = "invalid input"
POOR_ALIGNMENT = "poor alignment"  # ran and converged, but fitness / RMSE fail the caller's gates


@dataclass
class RegistrationResult:
    """Result of aligning a source (frame, cloud) to a target.

    T_target_source [4, 4] float64 maps source-frame points into the target frame. When `success` is False it
    is the initial guess (never a half-converged pose), and `reason` says why ("too few points", "degenerate
    geometry", "not converged", "invalid input", "poor alignment").
    fitness: inlier correspondences / valid source points (Open3D's definition). inlier_rmse: RMS Euclidean
    distance over the inlier correspondences, metres (Open3D's definition).
    information [6, 6]: Open3D's `get_information_matrix_from_point_clouds` convention, sum over correspondences
    of G^T G with G = [-[q]x, I] at the target point q, twist order [omega, v] (rotation first, as kernels.se3
    and GTSAM), in the target frame.
    """

    T_target_source: np.ndarray
    success: bool
    reason: str = OK
    fitness: float = 0.0
    inlier_rmse: float = 0.0
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    iterations: int = 0
    n_correspondences: int = 0
    method: str = ""

    def passes(self, min_fitness: float, max_rmse: float) -> bool:
        """The loop-closure gate of the paper (f > tau_f and rho < tau_rho) on a successful result."""
        return bool(self.success and self.fitness > min_fitness and self.inlier_rmse < max_rmse)

    @classmethod
    def failure(cls, init: np.ndarray, reason: str, method: str = "", **kw) -> "RegistrationResult":
        return cls(np.array(init, dtype=np.float64, copy=True), False, reason, method=method, **kw)

    def __repr__(self) -> str:
        t = self.T_target_source[:3, 3]
        return (f"RegistrationResult({self.method or 'registration'}: success={self.success}, reason={self.reason!r}, "
                f"fitness={self.fitness:.4f}, inlier_rmse={self.inlier_rmse:.5f}, iterations={self.iterations}, "
                f"n_correspondences={self.n_correspondences}, t=[{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}])")
