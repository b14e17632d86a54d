"""Umeyama alignment (SE(3) or Sim(3)) of an estimated trajectory to ground truth, and pose association.

Both follow evo's definitions so the numbers match `evo_ape` / `evo_rpe`: association pairs stamps by
`slam.io.datasets.associate.match_nearest` starting from the shorter trajectory; alignment is Umeyama's closed form
on positions (Umeyama, PAMI 1991), y ~ s R x + t with x the estimate and y the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.errors import InputError

ALIGN_MODES = ("se3", "sim3", "none")


@dataclass(frozen=True)
class Sim3:
    """y = scale * R @ x + t, mapping estimate coordinates into the ground-truth frame."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]
    scale: float = 1.0

    @staticmethod
    def identity() -> "Sim3":
        return Sim3(np.eye(3), np.zeros(3), 1.0)

    def apply_to_poses(self, T: np.ndarray) -> np.ndarray:
        """[N, 4, 4] T_world_cam -> aligned poses: positions scaled, rotated and moved; orientations rotated."""
        T = np.asarray(T, dtype=np.float64)
        out = T.copy()
        out[..., :3, :3] = self.R @ T[..., :3, :3]
        out[..., :3, 3] = self.scale * (T[..., :3, 3] @ self.R.T) + self.t
        return out

    @property
    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous similarity."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool = False) -> Sim3:
    """Least-squares similarity (or rigid transform) taking points x [N, 3] onto y [N, 3].

    Raises InputError when the points are too degenerate to fix a rotation (fewer than 3 non-collinear).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"umeyama: expected two [N, 3] point sets, got {list(x.shape)} and {list(y.shape)}")
    n = len(x)
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    var_x = float((xc**2).sum()) / n
    cov = yc.T @ xc / n  # [3, 3]
    U, d, Vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise InputError(f"cannot align trajectories: the {n} matched positions are (nearly) collinear or "
                         f"identical; use --align none")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / var_x) if with_scale else 1.0
    return Sim3(R, my - s * R @ mx, s)


def alignment(T_gt: np.ndarray, T_est: np.ndarray, mode: str) -> Sim3:
    """The transform of `mode` ("se3", "sim3", "none") aligning estimated to ground-truth positions."""
    mode = check_align_mode(mode)
    if mode == "none":
        return Sim3.identity()
    return umeyama(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=(mode == "sim3"))


def check_align_mode(mode: str) -> str:
    m = str(mode).lower()
    if m not in ALIGN_MODES:
        raise InputError(f"unknown alignment {mode!r}; expected one of {', '.join(ALIGN_MODES)}")
    return m


@dataclass
class PosePairs:
    """Ground-truth and estimated poses paired by time: row k of each belongs to the same instant."""

    timestamps: np.ndarray  # [K] estimate's stamps (seconds, or indices for unstamped formats)
    T_gt: np.ndarray  # [K, 4, 4]
    T_est: np.ndarray  # [K, 4, 4]
    n_gt: int
    n_est: int

    @property
    def matched(self) -> int:
        return len(self.timestamps)


def associate_poses(t_gt: np.ndarray, T_gt: np.ndarray, t_est: np.ndarray, T_est: np.ndarray,
                    max_diff: float = 0.01, offset: float = 0.0, by_index: bool = False) -> PosePairs:
    """Pair poses as evo does: each stamp of the shorter trajectory takes its nearest in the longer one within
    `max_diff` seconds (`offset` is added to the estimate's stamps). `by_index` pairs row i with row i instead
    and requires equal lengths (formats without time). Non-finite poses are refused."""
    t_gt, t_est = np.asarray(t_gt, np.float64), np.asarray(t_est, np.float64)
    T_gt, T_est = np.asarray(T_gt, np.float64), np.asarray(T_est, np.float64)
    for name, t, T in (("ground truth", t_gt, T_gt), ("estimate", t_est, T_est)):
        if T.ndim != 3 or T.shape[1:] != (4, 4) or len(t) != len(T):
            raise InputError(f"{name}: expected [N] timestamps and [N, 4, 4] poses, got {list(t.shape)} and {list(T.shape)}")
        bad = ~np.isfinite(T).reshape(len(T), -1).all(1) | ~np.isfinite(t)
        if bad.any():
            raise InputError(f"{name}: pose {int(np.nonzero(bad)[0][0])} contains NaN or Inf")
    if by_index:
        if len(t_gt) != len(t_est):
            raise InputError(f"trajectories without timestamps must have equal length to pair by index: "
                             f"ground truth has {len(t_gt)} poses, estimate {len(t_est)}")
        i_gt = i_est = np.arange(len(t_gt))
    elif len(t_est) > len(t_gt):
        i_gt, i_est = _match(t_gt, t_est, max_diff, offset)
    else:
        i_est, i_gt = _match(t_est, t_gt, max_diff, -offset)
    if len(i_gt) == 0:
        raise InputError(f"no matching timestamps between ground truth ({len(t_gt)} poses, "
                         f"{_span(t_gt)}) and estimate ({len(t_est)} poses, {_span(t_est)}) within {max_diff} s")
    return PosePairs(t_est[i_est], T_gt[i_gt], T_est[i_est], len(t_gt), len(t_est))


def _match(t_short, t_long, max_diff, offset_long):
    from swarmsplat.slam.io.datasets.associate import match_nearest

    return match_nearest(t_short, t_long, max_diff, offset_long)


def _span(t: np.ndarray) -> str:
    return f"t in [{t.min():.6f}, {t.max():.6f}]" if len(t) else "empty"
