"""SE(3) and SO(3) in float64 NumPy, with the conventions of GTSAM so poses pass to the graph unchanged.

Conventions (used everywhere in swarmsplat):
- A pose is a 4x4 homogeneous matrix named by its frames: `T_world_cam` maps camera coordinates to world.
- A twist is `xi = [omega, v]` (rotation first, as GTSAM's Pose3.Logmap), and `exp(xi)` is the closed form
  with the left Jacobian, so `exp(log(T)) == T`.
- Quaternions carry their order in the name: `quat_wxyz` (Hamilton, scalar first) or `quat_xyzw` (TUM files,
  scipy). Functions accept batches with leading dimensions: `[..., 3]`, `[..., 4, 4]`.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

_EPS = 1e-10


def hat(w: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] skew-symmetric matrices, hat(w) @ x == cross(w, x)."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def vee(W: np.ndarray) -> np.ndarray:
    """[..., 3, 3] skew matrices -> [..., 3]."""
    W = np.asarray(W, dtype=np.float64)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: [..., 3] axis-angle -> [..., 3, 3] rotation matrices."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = hat(w)
    W2 = W @ W
    small = theta < 1e-5
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * W + b * W2


def so3_log(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation matrices -> [..., 3] axis-angle, accurate near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.zeros((flat.shape[0], 3))
    for k, M in enumerate(flat):
        cos = np.clip((np.trace(M) - 1.0) / 2.0, -1.0, 1.0)
        theta = np.arccos(cos)
        if theta < 1e-5:
            out[k] = vee(M - M.T) / 2.0 * (1.0 + theta**2 / 6.0)
        elif np.pi - theta < 1e-4:
            # Near pi: axis from the largest diagonal entry of (R + I) / 2 = a a^T.
            B = (M + np.eye(3)) / 2.0
            i = int(np.argmax(np.diag(B)))
            axis = B[:, i] / np.sqrt(max(B[i, i], _EPS))
            axis /= np.linalg.norm(axis)
            # Fix the sign with the antisymmetric part so that theta slightly below pi is consistent.
            s = vee(M - M.T)
            if np.dot(s, axis) < 0:
                axis = -axis
            out[k] = axis * theta
        else:
            out[k] = vee(M - M.T) * (theta / (2.0 * np.sin(theta)))
    return out.reshape(R.shape[:-2] + (3,))


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    W = hat(w)
    small = theta < 1e-5
    t = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + b * W + c * (W @ W)


def exp(xi: np.ndarray) -> np.ndarray:
    """[..., 6] twists [omega, v] -> [..., 4, 4] poses."""
    xi = np.asarray(xi, dtype=np.float64)
    if xi.shape[-1] != 6:
        raise InputError(f"se3.exp: expected twists of shape [..., 6], got {list(xi.shape)}")
    w, v = xi[..., :3], xi[..., 3:]
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = so3_exp(w)
    T[..., :3, 3] = (_left_jacobian(w) @ v[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def log(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] poses -> [..., 6] twists [omega, v]."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    v = np.linalg.solve(_left_jacobian(w), T[..., :3, 3:4])[..., 0]
    return np.concatenate([w, v], axis=-1)


def inverse(T: np.ndarray) -> np.ndarray:
    """Closed-form inverse of [..., 4, 4] rigid transforms."""
    T = np.asarray(T, dtype=np.float64)
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    Ti[..., 3, 3] = 1.0
    return Ti


def project_rigid(T: np.ndarray) -> np.ndarray:
    """The nearest rigid transform to each [..., 4, 4] T: rotation projected onto SO(3) by SVD (Frobenius-nearest),
    translation kept, bottom row (0, 0, 0, 1). Products of many poses drift off SE(3) by rounding, and `inverse`
    (a transpose) turns any drift into a scale error that grows with every further product: pipelines that store
    composed poses project them."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    T[..., :3, :3] = U @ Vt
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T


def rigidity_error(T: np.ndarray) -> float:
    """max |RᵀR − I| over [..., 4, 4] T: 0 for a rigid transform (a check for stored poses)."""
    R = np.asarray(T, dtype=np.float64)[..., :3, :3]
    return float(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()) if R.size else 0.0


def compose(*Ts: np.ndarray) -> np.ndarray:
    """compose(A, B, C) == A @ B @ C for [..., 4, 4] transforms."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] -> [..., 6, 6] adjoint for twists ordered [omega, v] (GTSAM's Pose3.AdjointMap)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    A = np.zeros(T.shape[:-2] + (6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., 3:, :3] = hat(t) @ R
    return A


def make(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose from rotation [..., 3, 3] and translation [..., 3]."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """[..., 4] quaternions (w, x, y, z), normalised here -> [..., 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _EPS) or not np.all(np.isfinite(q)):
        raise InputError("quaternion of zero length or with NaN/Inf")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 4] unit quaternions (w, x, y, z) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    out = np.zeros((flat.shape[0], 4))
    for k, M in enumerate(flat):
        tr = np.trace(M)
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [0.25 * s, (M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s]
        elif M[0, 0] > M[1, 1] and M[0, 0] > M[2, 2]:
            s = 2.0 * np.sqrt(1.0 + M[0, 0] - M[1, 1] - M[2, 2])
            q = [(M[2, 1] - M[1, 2]) / s, 0.25 * s, (M[0, 1] + M[1, 0]) / s, (M[0, 2] + M[2, 0]) / s]
        elif M[1, 1] > M[2, 2]:
            s = 2.0 * np.sqrt(1.0 + M[1, 1] - M[0, 0] - M[2, 2])
            q = [(M[0, 2] - M[2, 0]) / s, (M[0, 1] + M[1, 0]) / s, 0.25 * s, (M[1, 2] + M[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + M[2, 2] - M[0, 0] - M[1, 1])
            q = [(M[1, 0] - M[0, 1]) / s, (M[0, 2] + M[2, 0]) / s, (M[1, 2] + M[2, 1]) / s, 0.25 * s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[k] = q if q[0] >= 0 else -q
    return out.reshape(R.shape[:-2] + (4,))


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def from_tum(xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """TUM line parts (x y z, qx qy qz qw) -> [..., 4, 4]."""
    return make(quat_wxyz_to_matrix(quat_xyzw_to_wxyz(quat_xyzw)), xyz)


def to_tum(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[..., 4, 4] -> (xyz [..., 3], quat_xyzw [..., 4])."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), quat_wxyz_to_xyzw(matrix_to_quat_wxyz(T[..., :3, :3]))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle in radians of [..., 3, 3] rotations."""
    R = np.asarray(R, dtype=np.float64)
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


# ---- torch twins used on the differentiable path (tracking) -------------------------------------------------


def exp_torch(xi):
    """torch [..., 6] twist [omega, v] -> [..., 4, 4], differentiable (autograd), same closed form as `exp`."""
    import torch

    w, v = xi[..., :3], xi[..., 3:]
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2 + 1e-24)
    zero = torch.zeros_like(w[..., 0])
    W = torch.stack(
        [zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0], -w[..., 1], w[..., 0], zero], dim=-1
    ).reshape(w.shape[:-1] + (3, 3))
    W2 = W @ W
    small = theta < 1e-4
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-24))
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(W.shape)
    R = eye + a * W + b * W2
    V = eye + b * W + c * W2
    t = (V @ v[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)
