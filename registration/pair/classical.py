"""Classical pair registration: OpenCV features, Lowe's ratio test, essential matrix with a robust estimator
(USAC/MAGSAC++ by default, RANSAC on request) and pose recovery with the cheirality check.

Encoding: keypoints (float32 [N, 2], original-image pixels) and descriptors (uint8 [N, 128] for SIFT, uint8
[N, 32] for ORB). `n_correspondences` counts the matches that survive the essential matrix and the cheirality
check — the geometrically verified correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from .base import Encoding, PairRegistrar, PairResult
from .geometry import matched_pose

FEATURES = ("sift", "orb", "akaze")
ESTIMATORS = ("usac", "ransac")  # see geometry.essential_pose


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
        from swarmsplat.registration.images import as_rgb8, resize_max_side, to_grey

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
        return matched_pose(kq, km, pairs, camera_query, camera_match, min_matches=cfg.min_matches,
                            estimator=cfg.estimator, threshold_px=cfg.threshold_px, confidence=cfg.confidence,
                            min_inliers=cfg.min_inliers)
