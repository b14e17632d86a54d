"""Classical pair registration: OpenCV features, Lowe's ratio test, essential matrix with a robust estimator
(USAC/MAGSAC++ by default, RANSAC on request) and pose recovery with the cheirality check.

Encoding: keypoints (float32 [N, 2], original-image pixels) and descriptors (uint8 [N, 128] for SIFT, uint8
[N, 32] for ORB). `n_correspondences` counts the matches that survive the essential matrix and the cheirality
check — the geometrically verified correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels.camera import PinholeCamera
from kernels.errors import InputError

from .base import Encoding, PairRegistrar, PairResult, pose_from_essential_inverse

FEATURES = ("sift", "orb", "akaze")
ESTIMATORS = ("usac", "ransac")


@dataclass(frozen=True)
class ClassicalConfig:
    feature: str = "sift"  # sift | orb | akaze (akaze only where this OpenCV build ships it)
    n_features: int = 2000
    max_side: int = 1024  # images are downscaled to this longer side before detection
    ratio: float = 0.8  # Lowe's ratio test
    mutual: bool = True  # also require the match to be the best in the other direction
    estimator: str = "usac"  # usac (MAGSAC++) | ransac
    threshold_px: float = 1.0  # epipolar error threshold, pixels of the original images
    confidence: float = 0.999
    min_matches: int = 15
    min_inliers: int = 12


class ClassicalRegistrar(PairRegistrar):
    name = "classical"

    def __init__(self, config: ClassicalConfig | None = None, **overrides):
        cfg = config or ClassicalConfig()
        if overrides:
            cfg = ClassicalConfig(**{**cfg.__dict__, **overrides})
        if cfg.feature not in FEATURES:
            raise InputError(f"classical registration: feature must be one of {FEATURES}, got {cfg.feature!r}")
        if cfg.estimator not in ESTIMATORS:
            raise InputError(f"classical registration: estimator must be one of {ESTIMATORS}, got {cfg.estimator!r}")
        self.config = cfg
        self._detector = None

    def _make_detector(self):
        import cv2

        f = self.config.feature
        if f == "sift":
            return cv2.SIFT_create(nfeatures=self.config.n_features)
        if f == "orb":
            return cv2.ORB_create(nfeatures=self.config.n_features)
        if not hasattr(cv2, "AKAZE_create"):
            raise InputError("classical registration: feature 'akaze' is not in this OpenCV build "
                             f"({cv2.__version__}); use 'sift' or 'orb'")
        return cv2.AKAZE_create()

    def encode(self, image: np.ndarray) -> Encoding:
        from registration.images import as_rgb8, resize_max_side, to_grey

        rgb = as_rgb8(image)
        h, w = rgb.shape[:2]
        small, (sx, sy) = resize_max_side(rgb, self.config.max_side)
        if self._detector is None:
            self._detector = self._make_detector()
        kps, desc = self._detector.detectAndCompute(to_grey(small), None)
        dim = 128 if self.config.feature == "sift" else (32 if self.config.feature == "orb" else 61)
        if desc is None or not kps:
            kp = np.zeros((0, 2), np.float32)
            desc = np.zeros((0, dim), np.uint8)
        else:
            kp = np.array([k.pt for k in kps], np.float32)
            kp[:, 0] = (kp[:, 0] + 0.5) / sx - 0.5  # back to original-image pixels
            kp[:, 1] = (kp[:, 1] + 0.5) / sy - 0.5
            # SIFT values are already in [0, 255]; storing them as bytes quarters the encoding, matching barely moves
            desc = np.clip(np.rint(desc), 0, 255).astype(np.uint8) if desc.dtype != np.uint8 else desc
        return Encoding(self.name, (w, h), {"kp": kp, "desc": desc}, {"feature": self.config.feature})

    def _match(self, d_q: np.ndarray, d_m: np.ndarray) -> np.ndarray:
        """-> [M, 2] index pairs (query, match) passing the ratio (and mutual) test."""
        import cv2

        binary = self.config.feature != "sift"
        norm = cv2.NORM_HAMMING if binary else cv2.NORM_L2
        a, b = (d_q, d_m) if binary else (d_q.astype(np.float32), d_m.astype(np.float32))
        bf = cv2.BFMatcher(norm)
        knn = bf.knnMatch(a, b, k=2)
        pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn
                 if len(m) == 2 and m[0].distance < self.config.ratio * m[1].distance]
        if not pairs:
            return np.zeros((0, 2), int)
        pairs = np.array(pairs, int)
        if self.config.mutual:
            back = {m.queryIdx: m.trainIdx for m in bf.match(b, a)}
            keep = [back.get(j, -1) == i for i, j in pairs]
            pairs = pairs[np.array(keep, bool)]
        return pairs

    def register(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                 camera_match: PinholeCamera | None = None) -> PairResult:
        import cv2

        camera_match = self._check_inputs(enc_query, enc_match, camera_query, camera_match)
        cfg = self.config
        if enc_query.meta.get("feature") != enc_match.meta.get("feature"):
            raise InputError(f"classical.register: feature types differ ({enc_query.meta.get('feature')} vs "
                             f"{enc_match.meta.get('feature')})")
        kq, dq = enc_query.arrays["kp"], enc_query.arrays["desc"]
        km, dm = enc_match.arrays["kp"], enc_match.arrays["desc"]
        if len(kq) < 5 or len(km) < 5:
            return PairResult.failed(f"too few features ({len(kq)} and {len(km)})")
        try:
            pairs = self._match(dq, dm)
        except cv2.error as e:
            return PairResult.failed(f"matching failed: {str(e).strip().splitlines()[-1]}")
        pq, pm = kq[pairs[:, 0]].astype(np.float64), km[pairs[:, 1]].astype(np.float64)
        n = len(pairs)
        if n < max(cfg.min_matches, 5):
            return PairResult.failed(f"too few matches ({n} < {cfg.min_matches})", n_matches=n,
                                     points_query=pq, points_match=pm)
        # Normalised image coordinates let the two robots have different intrinsics.
        nq = (pq - [camera_query.cx, camera_query.cy]) / [camera_query.fx, camera_query.fy]
        nm = (pm - [camera_match.cx, camera_match.cy]) / [camera_match.fx, camera_match.fy]
        f_mean = np.mean([camera_query.fx, camera_query.fy, camera_match.fx, camera_match.fy])
        method = cv2.USAC_MAGSAC if cfg.estimator == "usac" else cv2.RANSAC
        try:
            E, mask = cv2.findEssentialMat(nq, nm, np.eye(3), method=method, prob=cfg.confidence,
                                           threshold=cfg.threshold_px / f_mean)
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
        ok = n_in >= cfg.min_inliers and np.all(np.isfinite(R_qm)) and np.linalg.norm(t_qm) > 0.5
        return PairResult(R_qm if ok else np.eye(3), t_qm if ok else np.zeros(3), n_in, n, bool(ok),
                          "" if ok else f"too few inliers ({n_in} < {cfg.min_inliers})",
                          inlier_mask=inliers, points_query=pq, points_match=pm)


def refine_relative_pose(R: np.ndarray, t: np.ndarray, xq: np.ndarray, xm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the Sampson error of x_m^T [t]x R x_q = 0 over the inliers (robust Cauchy loss).

    R, t: T_match_query as OpenCV's recoverPose gives it; xq, xm: [N, 2] normalised image coordinates.
    The minimal-sample estimate leaves a few degrees of error in the translation direction; a least-squares
    pass over all inliers removes most of it.
    """
    from scipy.optimize import least_squares

    from kernels import se3

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
