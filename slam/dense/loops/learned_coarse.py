"""A metric coarse guess for RGB-D loop candidates from learned matches: XFeat + LighterGlue pixel matches
(`registration.pair.xfeat`), lifted to 3-D with each view's depth, then a RANSAC rigid fit (Kabsch on 3-point
samples, refit on the inliers). Meant to replace the global FPFH + RANSAC start before ICP when two keyframes are
not yet in one frame: it needs no initial pose and costs one XFeat encoding per keyframe plus one matching.

Frames: x_match = T_match_query @ x_query (the query camera's points into the match camera), i.e. ICP's
`T_target_source` with source = query, target = match. Depth maps are metres, 0 = invalid, aligned with colour.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError


def lift(points_px: np.ndarray, depth: np.ndarray, camera: PinholeCamera, *, depth_max: float = np.inf,
         edge_rel: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [N, 2] (x, y) -> camera-frame points [N, 3] (metres) and a validity mask [N].

    A pixel is valid when its nearest depth is in (0, depth_max] and its 3x3 neighbourhood spans less than
    `edge_rel` of that depth (matches on depth edges would land on either surface).
    """
    h, w = depth.shape
    u = np.clip(np.rint(points_px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(points_px[:, 1]).astype(int), 0, h - 1)
    z = depth[v, u].astype(np.float64)
    pad = np.pad(depth, 1, mode="edge")
    nb = np.stack([pad[v + dy, u + dx] for dy in range(3) for dx in range(3)], 1)
    ok = (z > 0) & (z <= depth_max) & (nb.min(1) > 0) & (nb.max(1) - nb.min(1) < edge_rel * z)
    x = (points_px[:, 0] - camera.cx) / camera.fx * z
    y = (points_px[:, 1] - camera.cy) / camera.fy * z
    return np.stack([x, y, z], 1), ok


def kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rigid T [4, 4] minimising sum w |T P - Q|^2 for P, Q [N, 3] (batched: [B, N, 3] -> [B, 4, 4])."""
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    batched = P.ndim == 3
    if not batched:
        P, Q = P[None], Q[None]
    w = np.ones(P.shape[:2]) if w is None else np.broadcast_to(w, P.shape[:2])
    ws = w.sum(1, keepdims=True)[..., None]
    cp, cq = (w[..., None] * P).sum(1, keepdims=True) / ws, (w[..., None] * Q).sum(1, keepdims=True) / ws
    H = np.einsum("bn,bni,bnj->bij", w, P - cp, Q - cq)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))  # det(V U^T)
    D = np.zeros_like(H)
    D[:, 0, 0], D[:, 1, 1], D[:, 2, 2] = 1.0, 1.0, d
    R = np.einsum("bji,bjk,blk->bil", Vt, D, U)  # V D U^T
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = cq[:, 0] - np.einsum("bij,bj->bi", R, cp[:, 0])
    return T if batched else T[0]


def ransac_rigid(P: np.ndarray, Q: np.ndarray, *, threshold: float = 0.03, rel_threshold: float = 0.02,
                 iterations: int = 512, seed: int = 0) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust rigid fit Q ~ T P from [N, 3] correspondences with outliers -> (T [4, 4] or None, inlier mask [N]).

    A correspondence is an inlier when |T p - q| < threshold + rel_threshold * q_z (depth noise grows with
    range). Samples of 3 are drawn at once (seeded); the best hypothesis is refit on its inliers twice.
    """
    n = len(P)
    if n < 3:
        return None, np.zeros(n, bool)
    rng = np.random.default_rng(seed)
    idx = np.stack([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    idx = idx[area > 1e-4]  # drop (near-)collinear samples: 1 cm x 1 cm triangles and smaller
    if not len(idx):
        return None, np.zeros(n, bool)
    Ts = kabsch(P[idx], Q[idx])
    tol = threshold + rel_threshold * np.abs(Q[:, 2])
    res = np.linalg.norm(np.einsum("bij,nj->bni", Ts[:, :3, :3], P) + Ts[:, None, :3, 3] - Q[None], axis=2)
    score = (res < tol[None]).sum(1)
    best = Ts[int(np.argmax(score))]
    inl = np.linalg.norm(P @ best[:3, :3].T + best[:3, 3] - Q, axis=1) < tol
    for _ in range(2):
        if inl.sum() < 3:
            break
        best = kabsch(P[inl], Q[inl])
        inl = np.linalg.norm(P @ best[:3, :3].T + best[:3, 3] - Q, axis=1) < tol
    return best, inl


_REGISTRAR = {}


def _xfeat(top_k: int, max_side: int):
    key = (int(top_k), int(max_side))
    if key not in _REGISTRAR:
        from swarmsplat.registration.pair.xfeat import XFeatRegistrar

        _REGISTRAR[key] = XFeatRegistrar(top_k=top_k, max_side=max_side)
    return _REGISTRAR[key]


def coarse_guess_from_pair(color_q: np.ndarray, depth_q: np.ndarray, color_m: np.ndarray, depth_m: np.ndarray,
                           camera: PinholeCamera, *, enc_q=None, enc_m=None, top_k: int = 512, max_side: int = 640,
                           depth_max: float = np.inf, min_inliers: int = 15, min_inlier_ratio: float = 0.25,
                           threshold: float = 0.03, seed: int = 0) -> tuple[np.ndarray | None, dict]:
    """Metric T_match_query [4, 4] for an RGB-D pair without an initial guess, or None when it is not found.

    color_*: RGB uint8 [H, W, 3]; depth_*: float metres [H, W] (0 = invalid), both views on `camera`.
    enc_q / enc_m: `xfeat` Encodings of the two colour images when the robots already have them (skips encoding).
    Returns (T or None, info) with info = {"n_matches", "n_depth", "n_inliers", "inlier_rmse_m", "time_s",
    "reason"}; None when fewer than `min_inliers` 3-D matches (or under `min_inlier_ratio` of those with depth)
    agree. Refine the guess with ICP and gate it there: this is only the start.
    """
    t0 = time.perf_counter()
    for nm, d, c in (("depth_q", depth_q, color_q), ("depth_m", depth_m, color_m)):
        d = np.asarray(d)
        if d.ndim != 2 or d.shape != (camera.height, camera.width) or np.asarray(c).shape[:2] != d.shape:
            raise InputError(f"coarse_guess_from_pair: {nm} must be [{camera.height}, {camera.width}] like its "
                             f"colour image and the camera, got {list(d.shape)} (colour {list(np.asarray(c).shape)})")
    reg = _xfeat(top_k, max_side)
    lq = lifted(reg.encode(color_q) if enc_q is None else enc_q, depth_q, camera, depth_max=depth_max)
    lm = lifted(reg.encode(color_m) if enc_m is None else enc_m, depth_m, camera, depth_max=depth_max)
    T, info = guess_from_lifted(reg, lq, lm, min_inliers=min_inliers, min_inlier_ratio=min_inlier_ratio,
                                threshold=threshold, seed=seed)
    return T, info | {"time_s": time.perf_counter() - t0}


@dataclass
class Lifted:
    """A keyframe's XFeat encoding with its keypoints lifted once with the keyframe's depth."""

    encoding: object  # registration.pair.base.Encoding (backend 'xfeat')
    points: np.ndarray  # [N, 3] camera-frame metres, one per keypoint
    valid: np.ndarray  # [N] bool: depth valid and not on a depth edge (see `lift`)


def lifted(encoding, depth: np.ndarray, camera: PinholeCamera, *, depth_max: float = np.inf) -> Lifted:
    P, ok = lift(np.asarray(encoding.arrays["kp"], np.float64), np.asarray(depth), camera, depth_max=depth_max)
    return Lifted(encoding, P, ok)


def guess_from_lifted(reg, lq: Lifted, lm: Lifted, *, min_inliers: int = 15, min_inlier_ratio: float = 0.25,
                      threshold: float = 0.03, seed: int = 0) -> tuple[np.ndarray | None, dict]:
    """coarse_guess_from_pair's matching and RANSAC on two lifted encodings (`reg` the XFeat registrar that made
    them); info without "time_s"."""
    pairs = reg.match(lq.encoding, lm.encoding)
    info = {"n_matches": int(len(pairs)), "n_depth": 0, "n_inliers": 0, "inlier_rmse_m": float("nan")}
    if len(pairs) < min_inliers:
        return None, info | {"reason": f"too few matches ({len(pairs)} < {min_inliers})"}
    ok = lq.valid[pairs[:, 0]] & lm.valid[pairs[:, 1]]
    Pq, Pm = lq.points[pairs[ok, 0]], lm.points[pairs[ok, 1]]
    info["n_depth"] = int(ok.sum())
    if len(Pq) < min_inliers:
        return None, info | {"reason": f"too few matches with valid depth ({len(Pq)} < {min_inliers})"}
    T, inl = ransac_rigid(Pq, Pm, threshold=threshold, seed=seed)
    n_in = int(inl.sum())
    info["n_inliers"] = n_in
    if T is None or n_in < max(min_inliers, min_inlier_ratio * len(Pq)):
        return None, info | {"reason": f"too few rigid inliers ({n_in} of {len(Pq)})"}
    info["inlier_rmse_m"] = float(np.sqrt(np.mean(np.sum((Pq[inl] @ T[:3, :3].T + T[:3, 3] - Pm[inl]) ** 2, 1))))
    return T, info | {"reason": ""}


class KeyframeEncoder:
    """The server's cache of one XFeat encoding per keyframe (key: (agent, keyframe id)), its keypoints lifted
    with the keyframe's depth, made the first time the keyframe is needed and reused for every candidate it is in.
    Frames wider than `width` are downsampled to it first (the working resolution: at the 160-pixel loop-closure
    copies XFeat finds too few matches across viewpoints, see docs/grand-slam.md). `bytes` counts the encodings'
    wire size, `encode_s` / `guess_s` the time spent."""

    def __init__(self, *, top_k: int = 512, max_side: int = 640, min_inliers: int = 15, width: int = 320,
                 depth_max: float = np.inf):
        self.top_k, self.max_side, self.min_inliers = int(top_k), int(max_side), int(min_inliers)
        self.width, self.depth_max = int(width), float(depth_max)
        self.cache: dict = {}  # key -> Encoding
        self.lifted: dict = {}  # key -> Lifted
        self.bytes = 0
        self.encode_s = 0.0
        self.guess_s = 0.0
        self.guesses = 0
        self.found = 0

    def encode(self, key, rgbd):
        """The Encoding of keyframe `key` from its RGB-D view `rgbd` (slam.dense.frames.RGBD or PackedRGBD, any
        width), encoded and lifted on the first call only."""
        enc = self.cache.get(key)
        if enc is None:
            t0 = time.perf_counter()
            view = rgbd.resized(self.width) if rgbd.camera.width > self.width else rgbd
            view_depth = view.depth
            enc = self.cache[key] = _xfeat(self.top_k, self.max_side).encode(view.color)
            self.lifted[key] = lifted(enc, view_depth, view.camera, depth_max=self.depth_max)
            self.bytes += enc.nbytes
            self.encode_s += time.perf_counter() - t0
        return enc

    def guess(self, key_q, rgbd_q, key_m, rgbd_m) -> tuple[np.ndarray | None, dict]:
        """The coarse guess T_match_query between two keyframes (their views encoded if not cached yet)."""
        self.encode(key_q, rgbd_q)
        self.encode(key_m, rgbd_m)
        t0 = time.perf_counter()
        T, info = guess_from_lifted(_xfeat(self.top_k, self.max_side), self.lifted[key_q], self.lifted[key_m],
                                    min_inliers=self.min_inliers)
        info["time_s"] = time.perf_counter() - t0
        self.guesses += 1
        self.found += int(T is not None)
        self.guess_s += info["time_s"]
        return T, info

    def stats(self) -> dict:
        n = len(self.cache)
        return {"keyframes_encoded": n, "encoding_bytes": self.bytes, "bytes_per_keyframe": self.bytes / n if n else 0,
                "encode_width": self.width, "encode_s": self.encode_s, "guesses": self.guesses,
                "guesses_found": self.found, "guess_s": self.guess_s}
