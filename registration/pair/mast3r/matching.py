"""Dense matching and relative pose for MASt3R outputs.

`fast_reciprocal_nns`: MASt3R's fast reciprocal matching — start from a sparse pixel grid in image A, hop to the
nearest descriptor in B, back to the nearest in A, and repeat until the hop is a fixed point (a reciprocal pair);
both directions are run and the pairs merged. `pose_from_matches`: PnP (RANSAC + refinement) on view 1's pointmap
at the matched pixels against their matched pixels in view 2, giving T_2_1 and thus T_query_match.
"""

from __future__ import annotations

import numpy as np
import torch


@torch.no_grad()
def _nn(queries: torch.Tensor, db: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Index of the most similar (max dot product = min L2 for unit vectors) row of db for each query."""
    out = []
    for i in range(0, len(queries), chunk):
        out.append((queries[i : i + chunk] @ db.T).argmax(dim=1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.long)


@torch.no_grad()
def _one_way(desc_a: torch.Tensor, desc_b: torch.Tensor, wa: int, subsample: int, max_iter: int):
    ha = desc_a.shape[0] // wa
    ys, xs = np.mgrid[subsample // 2 : ha : subsample, subsample // 2 : wa : subsample].reshape(2, -1)
    ia = torch.as_tensor(np.unique(xs + wa * ys), dtype=torch.long)
    ib = torch.full_like(ia, -1)
    active = torch.ones(len(ia), dtype=torch.bool)
    for _ in range(max_iter):
        if not active.any():
            break
        new_b = _nn(desc_a[ia[active]], desc_b)
        moved_b = new_b != ib[active]
        ib[active] = new_b
        new_a = _nn(desc_b[ib[active]], desc_a)
        moved_a = new_a != ia[active]
        ia[active] = new_a
        idx = torch.nonzero(active).ravel()
        active[idx] = moved_a | moved_b  # converged once neither hop moves
    return ia[~active].numpy(), ib[~active].numpy()


@torch.no_grad()
def fast_reciprocal_nns(desc_a: torch.Tensor, desc_b: torch.Tensor, *, subsample: int = 8, max_iter: int = 10):
    """desc_a [Ha, Wa, D], desc_b [Hb, Wb, D] unit descriptors -> (xy_a [M, 2], xy_b [M, 2]) int pixel coordinates
    of unique reciprocal nearest-neighbour pairs, seeded from a grid every `subsample` pixels in both images."""
    ha, wa, d = desc_a.shape
    hb, wb, _ = desc_b.shape
    fa, fb = desc_a.reshape(-1, d).float(), desc_b.reshape(-1, d).float()
    a1, b1 = _one_way(fa, fb, wa, subsample, max_iter)
    b2, a2 = _one_way(fb, fa, wb, subsample, max_iter)
    pairs = np.unique(np.stack([np.r_[a1, a2], np.r_[b1, b2]], 1), axis=0) if len(a1) + len(a2) else np.zeros((0, 2), int)
    xy_a = np.stack([pairs[:, 0] % wa, pairs[:, 0] // wa], 1)
    xy_b = np.stack([pairs[:, 1] % wb, pairs[:, 1] // wb], 1)
    return xy_a, xy_b


def pose_from_matches(pts3d_1: np.ndarray, xy1: np.ndarray, xy2: np.ndarray, K2: np.ndarray, *,
                      reproj_px: float = 5.0, min_inliers: int = 12):
    """PnP of view 1's 3D points (view-1 frame) at xy1 against pixels xy2 of view 2 with intrinsics K2.

    pts3d_1: [H, W, 3]; xy1, xy2: [M, 2] pixels. Returns (R, t, inlier_mask, reason): R, t are T_2_1
    (x_2 = R x_1 + t), or None with a reason when PnP fails.
    """
    import cv2

    obj = pts3d_1[xy1[:, 1], xy1[:, 0]].astype(np.float64)
    img = xy2.astype(np.float64)
    ok = np.isfinite(obj).all(1)
    if ok.sum() < max(6, min_inliers):
        return None, None, np.zeros(len(xy1), bool), f"too few matches for PnP ({int(ok.sum())})"
    try:
        found, rvec, tvec, inl = cv2.solvePnPRansac(obj[ok], img[ok], K2, None, iterationsCount=1000,
                                                    reprojectionError=reproj_px, confidence=0.999,
                                                    flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error as e:
        return None, None, np.zeros(len(xy1), bool), f"PnP failed: {str(e).strip().splitlines()[-1]}"
    mask = np.zeros(len(xy1), bool)
    if not found or inl is None or len(inl) < min_inliers:
        return None, None, mask, f"PnP found {0 if inl is None else len(inl)} inliers (< {min_inliers})"
    mask[np.flatnonzero(ok)[inl.ravel()]] = True
    try:
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], K2, None, rvec, tvec)
    except cv2.error:
        pass
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.ravel(), mask, ""
