"""Information matrices: SE-Sync's isotropic weights, and what to do with ones that are not positive definite.

Matrices here are 6x6 in GTSAM's order (rotation rows/cols 0-2, translation 3-5). A 2D edge read from SE2 g2o
keeps its 3x3 (x, y, theta) information at rows/cols (3, 4, 2) and the identity elsewhere.

Policies for a matrix that is not symmetric positive definite (`--information` of `swarmsplat graph solve`):

  strict     refuse the file (InputError naming file:line and the eigenvalues).
  repair     (default) the nearest symmetric positive-definite matrix in the Frobenius norm (Higham 1988): the
             eigenvalues below a floor are raised to it, eigenvectors kept. The floor is REPAIR_FLOOR times the
             largest eigenvalue, so a direction the matrix says nothing (or something negative) about becomes a
             weak constraint, never a strong one. That is right for a matrix that misses positive definiteness
             by a little (rounding, a marginal covariance that lost a digit). A matrix that the projection would
             change by more than REPAIR_MAX_CHANGE of its Frobenius norm is not a slightly wrong covariance: its
             cross terms are not to be trusted, and the projection keeps them (measured on the synthetic graph
             of tests/test_graph_information.py with only its five grossly indefinite rotation-translation
             blocks: the projection moves the solution 0.29 m from the one with the true matrices, the
             isotropic weights 0.05 m; with its five slightly wrong ones added, this rule 0.17 m, isotropic
             weights for all ten 0.46 m, ignoring the ten edges 0.71 m). Such
             a matrix, and one with no positive eigenvalue, gets the isotropic matrix below instead.
  isotropic  SE-Sync's isotropic reduction of the two diagonal blocks (each block made positive definite first
             as in `repair` if it is not): rotation (3 / tr(Omega_R^-1)) I, translation (3 / tr(Omega_t^-1)) I
             (2D: theta weight I33, translation 2 / tr(Omega_t^-1)). The cross blocks are dropped.

Positive-definite matrices are never changed. The matrix as read stays on the edge (`Edge.info_raw`) so that the
SE-Sync objective, which uses only the diagonal blocks of the file's matrix, is SE-Sync's own on such files.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.errors import InputError

POLICIES = ("repair", "isotropic", "strict")
REPAIR_FLOOR = 1e-6  # smallest eigenvalue after `repair`, relative to the largest
REPAIR_MAX_CHANGE = 0.05  # `repair` projects only matrices it changes by at most this (relative Frobenius norm)
_IDX_2D = [3, 4, 2]  # x, y, theta inside the 6x6 matrix of a 2D edge
_DIAG = np.diag_indices(6)


def is_positive_definite(info: np.ndarray) -> np.ndarray:
    """[..., n, n] -> [...] bool: symmetric part has all eigenvalues > 1e-12 * max |entry| (what Cholesky needs
    with room to spare)."""
    info = np.asarray(info, float)
    scale = np.abs(info).max(axis=(-2, -1))
    # Divided by the largest entry first: the test is scale-free, and entries near the float range (1e308 in a
    # file) do not overflow into a matrix LAPACK cannot decompose.
    unit = info / np.where(scale > 0, scale, 1.0)[..., None, None]
    return np.linalg.eigvalsh(0.5 * (unit + np.swapaxes(unit, -1, -2)))[..., 0] > 1e-12


def nearest_pd(A: np.ndarray, floor: float = REPAIR_FLOOR) -> np.ndarray | None:
    """Nearest symmetric positive-definite matrix to A [n, n] in the Frobenius norm with eigenvalues >= floor *
    lambda_max; None if A has no positive eigenvalue."""
    s = float(np.abs(A).max())
    if not s > 0:
        return None
    S = 0.5 * (A / s + A.T / s)  # unit scale, as in is_positive_definite
    w, V = np.linalg.eigh(S)
    if not w[-1] > 0:
        return None
    w = np.maximum(w, floor * w[-1])
    return ((V * w) @ V.T) * s


def _block_weight(B: np.ndarray, dim: int) -> float | None:
    """dim / tr(B^-1) of a diagonal block (made positive definite first); None when it has no positive part."""
    if not is_positive_definite(B):
        B = nearest_pd(B)
        if B is None:
            return None
    return float(dim / np.trace(np.linalg.inv(B)))


def isotropic_information(info: np.ndarray, is_2d: bool = False) -> np.ndarray | None:
    """The `isotropic` policy's 6x6 matrix (module docstring); None when a diagonal block has no positive part."""
    if is_2d:
        w_r = float(info[2, 2]) if info[2, 2] > 0 else None
        w_t = _block_weight(info[3:5, 3:5], 2)
        if w_r is None or w_t is None:
            return None
        out = np.eye(6)
        out[2, 2], out[3, 3], out[4, 4] = w_r, w_t, w_t
        return out
    w_r, w_t = _block_weight(info[:3, :3], 3), _block_weight(info[3:, 3:], 3)
    if w_r is None or w_t is None:
        return None
    return np.diag([w_r] * 3 + [w_t] * 3)


def apply_policy(info: np.ndarray, policy: str, is_2d: bool = False) -> tuple[np.ndarray, str] | None:
    """A positive-definite replacement for the non-positive-definite `info` [6, 6] under `policy`, with the rule
    that produced it ("repair" or "isotropic"); None when no replacement exists (or policy is strict)."""
    if policy not in POLICIES:
        raise InputError(f"information policy must be one of {POLICIES}, got {policy!r}")
    if policy == "strict":
        return None
    if policy == "repair":
        A = info[np.ix_(_IDX_2D, _IDX_2D)] if is_2d else info
        B = nearest_pd(A)
        if B is not None and np.linalg.norm(B - A) <= REPAIR_MAX_CHANGE * np.linalg.norm(A):
            if not is_2d:
                return B, "repair"
            out = np.eye(6)
            out[np.ix_(_IDX_2D, _IDX_2D)] = B
            return out, "repair"
    iso = isotropic_information(info, is_2d)
    return None if iso is None else (iso, "isotropic")


def isotropic_weights(info: np.ndarray, is_2d: bool = False):
    """SE-Sync's (kappa, tau) of an edge from its 6x6 GTSAM-ordered information matrix, as SE-Sync's g2o reader
    computes them (SESync_utils.cpp; the PROVENANCE of the SE-Sync data):
        3D: tau = 3 / tr(Omega_t^-1), kappa = 3 / (2 tr(Omega_R^-1));   2D: tau = 2 / tr(Omega_t^-1), kappa = I33.
    kappa weighs ||R_j - R_i R_ij||_F^2 (which is ~2 theta^2 for a small angle theta), tau ||t_j - t_i - R_i t_ij||^2.
    One [6, 6] matrix -> two floats; a batch [E, 6, 6] -> two [E] arrays."""
    info = np.asarray(info, float)
    if is_2d:
        kappa = info[..., 2, 2]
        tau = 2.0 / np.trace(np.linalg.inv(info[..., 3:5, 3:5]), axis1=-2, axis2=-1)
    else:
        tau = 3.0 / np.trace(np.linalg.inv(info[..., 3:, 3:]), axis1=-2, axis2=-1)
        kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(info[..., :3, :3]), axis1=-2, axis2=-1))
    if info.ndim == 2:
        return float(kappa), float(tau)
    return kappa, tau


def diagonal_weights(info: np.ndarray, is_2d: bool = False) -> tuple[float, float]:
    """`isotropic_weights` of a diagonal matrix (such as `se_sync_information`'s), without inverses."""
    d = np.diagonal(info).tolist()  # plain floats: this runs once per edge when factors are built
    if is_2d:
        return d[2], 2.0 / (1.0 / d[3] + 1.0 / d[4])
    return 1.5 / (1.0 / d[0] + 1.0 / d[1] + 1.0 / d[2]), 3.0 / (1.0 / d[3] + 1.0 / d[4] + 1.0 / d[5])


def se_sync_weights(edges, is_2d: bool = False) -> np.ndarray:
    """[E, 2] SE-Sync (kappa, tau) of graph edges (one edge: a pair of floats), times each edge's confidence:
    from the file's own matrix where it was replaced, each weight whose diagonal block still gives a positive
    value (what SE-Sync itself uses), else from the matrix in use."""
    if not isinstance(edges, (list, tuple)):
        k, t = se_sync_weights([edges], is_2d)[0]
        return float(k), float(t)
    if not edges:
        return np.zeros((0, 2))
    conf = np.array([e.confidence for e in edges])
    k, t = isotropic_weights(np.stack([e.info for e in edges]), is_2d)
    out = np.stack([k, t], axis=1)
    raw = [n for n, e in enumerate(edges) if e.info_raw is not None]
    for n in raw:
        try:
            w = np.array(isotropic_weights(edges[n].info_raw, is_2d))
        except np.linalg.LinAlgError:
            continue
        ok = np.isfinite(w) & (w > 0)  # per weight: a block of the file's matrix that is itself not PD is not used
        out[n, ok] = w[ok]
    return out * conf[:, None]


def se_sync_information(kappa: float, tau: float, is_2d: bool = False) -> np.ndarray:
    """A 6x6 diagonal matrix whose `isotropic_weights` are (kappa, tau): what the se-sync objective's factors are
    built from (diag(2 kappa I, tau I); 2D: theta kappa, x and y tau, identity elsewhere)."""
    out = np.zeros((6, 6))
    if is_2d:
        out[_DIAG] = (1.0, 1.0, kappa, tau, tau, 1.0)
    else:
        k2 = 2.0 * kappa
        out[_DIAG] = (k2, k2, k2, tau, tau, tau)
    return out
