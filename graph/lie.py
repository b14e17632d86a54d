"""Batched SE(3) operations in float64 NumPy with GTSAM's conventions, for factors evaluated many at a time.

Poses are [..., 4, 4] matrices, twists `xi = [omega, v]` (rotation first), perturbations on the right
(`T <- T @ exp(xi)`), exactly as `gtsam.Pose3.retract/Logmap/LogmapDerivative/AdjointMap`. `kernels.se3` has
the same maps for a handful of poses; these are vectorised over thousands of loop closures per call (one
solver iteration), with no Python loop over elements.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.se3 import hat, inverse  # already batched over leading dimensions

_SMALL = 1e-4  # below this angle (rad) the closed forms lose digits; Taylor series are exact to ~1e-16 there


def between(Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """Ta^-1 @ Tb, batched: [..., 4, 4]."""
    return inverse(Ta) @ Tb


def adjoint(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] -> [..., 6, 6] adjoint for [omega, v] twists: [[R, 0], [t^ R, R]] (gtsam.Pose3.AdjointMap)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = hat(t) @ R
    return out


def so3_log(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 3] axis-angle, accurate near 0 and near pi."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.sin(theta)
    small = theta < _SMALL
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    out = skew * scale[..., None]
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):
        # sin(theta) ~ 0: take the axis from the symmetric part (R + I) / 2 = a a^T (+ O(pi - theta)).
        Rp = R[near_pi]
        B = (Rp + np.eye(3)) / 2.0
        i = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(len(Rp)), :, i] / np.sqrt(np.maximum(B[np.arange(len(Rp)), i, i], 1e-12))[:, None]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sgn = np.where(np.einsum("ni,ni->n", skew[near_pi], axis) < 0, -1.0, 1.0)
        out[near_pi] = axis * (sgn * theta[near_pi])[:, None]
    return out


def so3_exp(w: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] Rodrigues."""
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    W = hat(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def _so3_jr_inv(w: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3): I + W/2 + (1/th^2 - 1/(2 th tan(th/2))) W^2."""
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0, 1.0 / t**2 - 1.0 / (2.0 * t * np.tan(t / 2.0)))
    W = hat(w)
    return np.eye(3) + 0.5 * W + c[..., None, None] * (W @ W)


def _so3_jr(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    W = hat(w)
    return np.eye(3) - a[..., None, None] * W + b[..., None, None] * (W @ W)


def _q_left(rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Barfoot's Q(rho, phi), the coupling block of the SE(3) left Jacobian."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-2  # the c3 closed form cancels badly below ~1e-2; the series is exact to 1e-16 there
    t = np.where(small, 1.0, theta)
    c1 = np.where(small, 1 / 6 - theta**2 / 120 + theta**4 / 5040, (t - np.sin(t)) / t**3)
    c2 = np.where(small, 1 / 24 - theta**2 / 720 + theta**4 / 40320, (t**2 + 2 * np.cos(t) - 2) / (2 * t**4))
    c3 = np.where(small, 1 / 120 - theta**2 / 2520 + theta**4 / 120960,
                  (2 * t - 3 * np.sin(t) + t * np.cos(t)) / (2 * t**5))
    P, Rh = hat(phi), hat(rho)
    PR, RP = P @ Rh, Rh @ P
    PRP = PR @ P
    return (0.5 * Rh + c1[..., None, None] * (PR + RP + PRP)
            + c2[..., None, None] * (P @ PR + RP @ P - 3.0 * PRP)
            + c3[..., None, None] * (PRP @ P + P @ PRP))


def log(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] -> [..., 6] twist [omega, v] with exp(log(T)) == T (gtsam.Pose3.Logmap)."""
    w = so3_log(T[..., :3, :3])
    # translation part: v = J_l(w)^-1 t = J_r(-w)^-1 t = J_r(w)^-T t
    v = np.einsum("...ji,...j->...i", _so3_jr_inv(w), T[..., :3, 3])
    return np.concatenate([w, v], axis=-1)


def exp(xi: np.ndarray) -> np.ndarray:
    """[..., 6] [omega, v] -> [..., 4, 4] (gtsam.Pose3.Expmap)."""
    w, v = xi[..., :3], xi[..., 3:]
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = so3_exp(w)
    # J_l(w) = J_r(w)^T
    out[..., :3, 3] = np.einsum("...ji,...j->...i", _so3_jr(w), v)
    out[..., 3, 3] = 1.0
    return out


def right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """[..., 6] -> [..., 6, 6] inverse right Jacobian of SE(3) (gtsam.Pose3.LogmapDerivative at Expmap(xi))."""
    w, v = xi[..., :3], xi[..., 3:]
    Ainv = _so3_jr_inv(w)
    Q = _q_left(-v, -w)  # J_r(xi) = J_l(-xi); in [omega, v] order its lower-left block is Q(-v, -w)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ainv
    out[..., 3:, 3:] = Ainv
    out[..., 3:, :3] = -Ainv @ Q @ Ainv
    return out
