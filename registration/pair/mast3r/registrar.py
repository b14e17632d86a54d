"""MASt3R as a pair-registration backend with the encode/decode split of FLOCC-SLAM.

encode(image): resize the longer side to the model size (512), centre-crop to a multiple of the patch size,
    normalise to [-1, 1], run the ViT encoder; the Encoding carries the tokens (float16 by default) and the
    resize/crop that relates network pixels to the original image.
register(enc_q, enc_m, cam_q, cam_m): decoder + heads for the pair, fast reciprocal matching of the local
    descriptors (minus a border and low-confidence pixels), PnP on the query's pointmap -> T_query_match with a
    unit translation. `n_correspondences` = reciprocal matches (the count FLOCC's eq. (1) uses).

Without a checkpoint, `Mast3rRegistrar.from_checkpoint(None)` raises one InputError line; nothing is downloaded.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from ..base import Encoding, PairRegistrar, PairResult
from .matching import fast_reciprocal_nns, pose_from_matches
from .model import EncodedImage, Mast3rConfig, Mast3rNet, grid_positions


def load_mast3r_checkpoint(path, device: str = "cpu", *, trust_checkpoint: bool = False) -> Mast3rNet:
    """Build the network described by an official checkpoint ({'model': state_dict, 'args': Namespace(model=...)})
    and load its weights strictly.

    The file is read with torch's safe loader (tensors and an argparse Namespace only). `trust_checkpoint=True`
    allows full unpickling, as the official code does, for a file from a source you trust that carries other objects.
    """
    if path is None:
        raise InputError("MASt3R: no checkpoint given; pass --checkpoint PATH to the official "
                         "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth (nothing is downloaded)")
    path = Path(path)
    if not path.is_file():
        raise InputError(f"MASt3R: checkpoint not found: {path}")
    torch.serialization.add_safe_globals([argparse.Namespace])
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=not trust_checkpoint)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
        hint = "" if trust_checkpoint else " (if the file is from a source you trust: trust_checkpoint=True)"
        raise InputError(f"MASt3R: cannot read checkpoint {path}: {type(e).__name__}: "
                         f"{str(e).strip().splitlines()[0]}{hint}") from None
    state = ckpt.get("model", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        raise InputError(f"MASt3R: {path} does not hold a state dict")
    model_str = getattr(ckpt.get("args", None), "model", None) if isinstance(ckpt, dict) else None
    cfg = Mast3rConfig.from_model_string(model_str) if model_str else Mast3rConfig()
    if not any(k.startswith("dec_blocks2") for k in state):  # DUSt3R-style checkpoints share the decoder
        state = {**state, **{k.replace("dec_blocks", "dec_blocks2"): v for k, v in state.items()
                             if k.startswith("dec_blocks.")}}
    from swarmsplat.registration.place_recognition.backbones import load_into

    # Build on the meta device: no memory and no random initialisation for 0.7 G parameters, and a checkpoint
    # that does not fit is refused before anything is allocated; `assign` then adopts the loaded tensors.
    with torch.device("meta"):
        net = Mast3rNet(cfg)
    load_into(net, state, "MASt3R", path, assign=True)
    return net.to(device).eval()


class Mast3rRegistrar(PairRegistrar):
    name = "mast3r"

    def __init__(self, net: Mast3rNet, *, device: str = "cpu", size: int | None = None, token_dtype: str = "float16",
                 subsample: int = 8, border: int = 3, min_desc_conf: float = 0.0, reproj_px: float = 5.0,
                 min_inliers: int = 12):
        if token_dtype not in ("float16", "float32"):
            raise InputError(f"MASt3R: token_dtype must be float16 or float32, got {token_dtype!r}")
        self.net = net.eval().to(device)
        self.device = device
        self.size = int(size or net.cfg.img_size)
        self.token_dtype = token_dtype
        self.subsample, self.border = int(subsample), int(border)
        self.min_desc_conf, self.reproj_px, self.min_inliers = float(min_desc_conf), float(reproj_px), int(min_inliers)

    @classmethod
    def from_checkpoint(cls, path, *, device: str = "cpu", trust_checkpoint: bool = False, **kw) -> "Mast3rRegistrar":
        return cls(load_mast3r_checkpoint(path, device, trust_checkpoint=trust_checkpoint), device=device, **kw)

    # ---- image <-> network frame -------------------------------------------------------------------------------

    def preprocess(self, rgb: np.ndarray) -> tuple[torch.Tensor, dict]:
        """RGB uint8 [H, W, 3] -> ([1, 3, h, w] in [-1, 1], meta with scale (sx, sy) and crop offset (x0, y0))."""
        import cv2

        h, w = rgb.shape[:2]
        p = self.net.cfg.patch_size
        s = self.size / max(h, w)
        nw, nh = max(p, round(w * s)), max(p, round(h * s))
        img = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC)
        cw, ch = (nw // p) * p, (nh // p) * p
        if cw == ch:  # as the official loader: square images are cropped to 4:3, the aspect MASt3R was trained on
            ch = max(p, (cw * 3 // 4) // p * p)
        x0, y0 = (nw - cw) // 2, (nh - ch) // 2
        img = img[y0 : y0 + ch, x0 : x0 + cw]
        x = torch.from_numpy(np.ascontiguousarray(img)).float().div_(127.5).sub_(1.0).permute(2, 0, 1)[None]
        return x, {"sx": nw / w, "sy": nh / h, "x0": x0, "y0": y0, "h": ch, "w": cw}

    @staticmethod
    def network_camera(cam: PinholeCamera, meta: dict) -> PinholeCamera:
        """The camera seen by the network: `cam` resized then cropped as `preprocess` did."""
        sc = cam.scaled(round(cam.width * meta["sx"]), round(cam.height * meta["sy"]))
        return PinholeCamera(sc.fx, sc.fy, sc.cx - meta["x0"], sc.cy - meta["y0"], meta["w"], meta["h"])

    @staticmethod
    def to_original(xy: np.ndarray, meta: dict) -> np.ndarray:
        """Network pixels [M, 2] -> original-image pixels."""
        x = (xy[:, 0] + meta["x0"] + 0.5) / meta["sx"] - 0.5
        y = (xy[:, 1] + meta["y0"] + 0.5) / meta["sy"] - 0.5
        return np.stack([x, y], 1)

    # ---- encode / decode ---------------------------------------------------------------------------------------

    @torch.no_grad()
    def encode(self, image: np.ndarray) -> Encoding:
        from swarmsplat.registration.images import as_rgb8

        rgb = as_rgb8(image, min_side=self.net.cfg.patch_size)
        x, meta = self.preprocess(rgb)
        e = self.net.encode(x.to(self.device))
        tokens = e.tokens[0].to(getattr(torch, self.token_dtype)).cpu().numpy()  # [N, enc_dim]
        return Encoding(self.name, (rgb.shape[1], rgb.shape[0]), {"tokens": tokens}, meta)

    def _encoded(self, enc: Encoding) -> EncodedImage:
        m = enc.meta
        p = self.net.cfg.patch_size
        gh, gw = m["h"] // p, m["w"] // p
        tok = torch.from_numpy(np.asarray(enc.arrays["tokens"], np.float32))
        if tok.shape != (gh * gw, self.net.cfg.enc_embed_dim):
            raise InputError(f"mast3r: encoding holds tokens {list(tok.shape)}, this model expects "
                             f"[{gh * gw}, {self.net.cfg.enc_embed_dim}] (made by another model?)")
        return EncodedImage(tok[None].to(self.device), grid_positions(1, gh, gw, self.device), (m["h"], m["w"]))

    @torch.no_grad()
    def decode(self, enc_query: Encoding, enc_match: Encoding) -> tuple[dict, dict]:
        """Run the decoder and heads on two encodings -> (view1, view2) dicts of numpy arrays (batch removed)."""
        o1, o2 = self.net.decode(self._encoded(enc_query), self._encoded(enc_match))
        return ({k: v[0].float().cpu().numpy() for k, v in o1.items()},
                {k: v[0].float().cpu().numpy() for k, v in o2.items()})

    def register(self, enc_query: Encoding, enc_match: Encoding, camera_query: PinholeCamera,
                 camera_match: PinholeCamera | None = None) -> PairResult:
        camera_match = self._check_inputs(enc_query, enc_match, camera_query, camera_match)
        o1, o2 = self.decode(enc_query, enc_match)
        xy1, xy2 = fast_reciprocal_nns(torch.from_numpy(o1["desc"]), torch.from_numpy(o2["desc"]),
                                       subsample=self.subsample)
        keep = np.ones(len(xy1), bool)
        for xy, o in ((xy1, o1), (xy2, o2)):
            h, w = o["desc"].shape[:2]
            b = self.border
            keep &= (xy[:, 0] >= b) & (xy[:, 0] < w - b) & (xy[:, 1] >= b) & (xy[:, 1] < h - b)
            if self.min_desc_conf > 0:
                keep &= o["desc_conf"][xy[:, 1], xy[:, 0]] >= self.min_desc_conf
        xy1, xy2 = xy1[keep], xy2[keep]
        n = len(xy1)
        pq, pm = self.to_original(xy1, enc_query.meta), self.to_original(xy2, enc_match.meta)
        extras = {"mean_conf_query": float(o1["conf"].mean()), "mean_conf_match": float(o2["conf"].mean())}
        K2 = self.network_camera(camera_match, enc_match.meta).K
        R21, t21, mask, reason = pose_from_matches(o1["pts3d"], xy1, xy2, K2, reproj_px=self.reproj_px,
                                                   min_inliers=self.min_inliers)
        if R21 is None:
            return PairResult.failed(reason, n_matches=n, n_correspondences=n, inlier_mask=mask, points_query=pq,
                                     points_match=pm, extras=extras)
        R = R21.T
        t = -R21.T @ t21
        norm = np.linalg.norm(t)
        extras["translation_model_units"] = float(norm)  # MASt3R's own (unreliable) scale, kept for eq. (6) studies
        if norm < 1e-9 or not np.all(np.isfinite(R)):
            return PairResult.failed("degenerate pose (zero translation)", n_matches=n, n_correspondences=n,
                                     inlier_mask=mask, points_query=pq, points_match=pm, extras=extras)
        return PairResult(R, t / norm, n, n, True, "", inlier_mask=mask, points_query=pq, points_match=pm,
                          extras=extras)
