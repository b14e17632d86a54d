"""Relative pose up to scale from 2D-2D matches: essential matrix with a robust estimator (USAC/MAGSAC++ or
RANSAC), cheirality check (recoverPose), then a least-squares refinement of the Sampson error over the inliers;
or, with estimator 'poselib', PoseLib's LO-RANSAC relative pose (five-point solver with its cheirality test and
a Cauchy-loss refinement built in; ~10x faster). Shared by the classical and learned-matcher backends.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera

from .base import PairResult, import_optional, pose_from_essential_inverse


def essential_pose(pq: np.ndarray, pm: np.ndarray, camera_query: PinholeCamera, camera_match: PinholeCamera, *,
                   estimator: str = "usac", threshold_px: float = 1.0, confidence: float = 0.999,
                   min_inliers: int = 12) -> PairResult:
    """Matched pixels pq, pm [N, 2] (float64, original images) -> PairResult with T_query_match (unit t).

    n_correspondences counts the matches that pass the essential matrix and the cheirality check.
    estimator: 'usac' (OpenCV MAGSAC++), 'ransac' (OpenCV) or 'poselib' (needs the poselib package).
    """
    import cv2

    n = len(pq)
    if estimator == "poselib":
        return _poselib_pose(pq, pm, camera_query, camera_match, threshold_px, confidence, min_inliers)
    # Normalised image coordinates let the two robots have different intrinsics.
    nq = (pq - [camera_query.cx, camera_query.cy]) / [camera_query.fx, camera_query.fy]
    nm = (pm - [camera_match.cx, camera_match.cy]) / [camera_match.fx, camera_match.fy]
    f_mean = np.mean([camera_query.fx, camera_query.fy, camera_match.fx, camera_match.fy])
    method = cv2.USAC_MAGSAC if estimator == "usac" else cv2.RANSAC
    try:
        E, mask = cv2.findEssentialMat(nq, nm, np.eye(3), method=method, prob=confidence,
                                       threshold=threshold_px / f_mean)
        if E is None or E.shape[0] < 3:
            return PairResult.failed("no essential matrix found", n_matches=n, points_query=pq, points_match=pm)
        E = E[:3]
        mask = (mask.ravel() > 0).astype(np.uint8)
        _, R, t, mask2 = cv2.recoverPose(E, nq, nm, np.eye(3), mask=mask.copy())
    except cv2.error as e:
        return PairResult.failed(f"essential matrix failed: {str(e).strip().splitlines()[-1]}", n_matches=n,
                                 points_query=pq, points_match=pm)
    inliers = mask2.ravel() > 0
    n_in = int(inliers.sum())
    if n_in >= 8:
        R, t = refine_relative_pose(R, t.ravel(), nq[inliers], nm[inliers])
    R_qm, t_qm = pose_from_essential_inverse(R, t)
    ok = n_in >= min_inliers and np.all(np.isfinite(R_qm)) and np.linalg.norm(t_qm) > 0.5
    return PairResult(R_qm if ok else np.eye(3), t_qm if ok else np.zeros(3), n_in, n, bool(ok),
                      "" if ok else f"too few inliers ({n_in} < {min_inliers})",
                      inlier_mask=inliers, points_query=pq, points_match=pm)


def _poselib_pose(pq, pm, camera_query, camera_match, threshold_px, confidence, min_inliers) -> PairResult:
    """`essential_pose` through PoseLib: the five-point solver in LO-RANSAC (points behind either camera are
    rejected inside the solver) and a Cauchy-loss bundle refinement of the epipolar error over the inliers."""
    poselib = import_optional("poselib", "estimator 'poselib' needs the package poselib (pip install poselib)")

    def cam(c):
        return {"model": "PINHOLE", "width": int(c.width), "height": int(c.height),
                "params": [float(c.fx), float(c.fy), float(c.cx), float(c.cy)]}

    pose, info = poselib.estimate_relative_pose(pq, pm, cam(camera_query), cam(camera_match),
                                                {"max_epipolar_error": float(threshold_px),
                                                 "success_prob": float(confidence)}, {})
    inliers = np.asarray(info.get("inliers", []), bool)
    n_in = int(inliers.sum()) if len(inliers) == len(pq) else 0
    R_qm, t_qm = pose_from_essential_inverse(np.asarray(pose.R), np.asarray(pose.t))  # pose: x_m = R x_q + t
    ok = n_in >= min_inliers and np.all(np.isfinite(R_qm)) and np.linalg.norm(t_qm) > 0.5
    return PairResult(R_qm if ok else np.eye(3), t_qm if ok else np.zeros(3), n_in, len(pq), bool(ok),
                      "" if ok else f"too few inliers ({n_in} < {min_inliers})",
                      inlier_mask=inliers if len(inliers) == len(pq) else np.zeros(len(pq), bool),
                      points_query=pq, points_match=pm)


def matched_pose(kq: np.ndarray, km: np.ndarray, pairs: np.ndarray, camera_query: PinholeCamera,
                 camera_match: PinholeCamera, *, min_matches: int = 15, **essential) -> PairResult:
    """Keypoints kq [Nq, 2], km [Nm, 2] and matched index pairs [S, 2] -> `essential_pose` of the matched pixels,
    or a failed result when fewer than `min_matches` (at least 5) matches exist. `essential`: its keyword options."""
    pq, pm = kq[pairs[:, 0]].astype(np.float64), km[pairs[:, 1]].astype(np.float64)
    if len(pairs) < max(min_matches, 5):
        return PairResult.failed(f"too few matches ({len(pairs)} < {min_matches})", n_matches=len(pairs),
                                 points_query=pq, points_match=pm)
    return essential_pose(pq, pm, camera_query, camera_match, **essential)


def refine_relative_pose(R: np.ndarray, t: np.ndarray, xq: np.ndarray, xm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the Sampson error of x_m^T [t]x R x_q = 0 over the inliers (robust Cauchy loss).

    R, t: T_match_query as OpenCV's recoverPose gives it; xq, xm: [N, 2] normalised image coordinates.
    The minimal-sample estimate leaves a few degrees of error in the translation direction; a least-squares
    pass over all inliers removes most of it.
    """
    from scipy.optimize import least_squares

    from swarmsplat.kernels import se3

    hq = np.c_[xq, np.ones(len(xq))]
    hm = np.c_[xm, np.ones(len(xm))]

    def residual(p):
        Rk = se3.so3_exp(p[:3]) @ R
        tk = p[3:] / max(np.linalg.norm(p[3:]), 1e-12)
        E = se3.hat(tk) @ Rk
        Ex, Etx = hq @ E.T, hm @ E
        num = np.einsum("ij,ij->i", hm, Ex)
        den = np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2) + 1e-15
        return num / den

    p0 = np.r_[np.zeros(3), t / np.linalg.norm(t)]
    scale = np.median(np.abs(residual(p0))) * 3 + 1e-9
    try:
        sol = least_squares(residual, p0, loss="cauchy", f_scale=scale, max_nfev=50)
    except (ValueError, np.linalg.LinAlgError):
        return R, t
    if not np.all(np.isfinite(sol.x)) or sol.cost > 0.5 * np.sum(np.square(residual(p0))):
        return R, t
    t_new = sol.x[3:] / np.linalg.norm(sol.x[3:])
    return se3.so3_exp(sol.x[:3]) @ R, t_new
