"""Real image pairs with known relative pose from a Redwood RGB-D sequence (colour, clean depth, trajectory.log).

`redwood_livingroom1_211`'s trajectory.log is Open3D's reconstruction estimate (pseudo ground truth, within 2 mm
and 0.07 deg of the true poses where checked; see its PROVENANCE): good enough to judge a relative pose at the
5 deg / 15 deg level. Pairs are sampled per rotation bin among frame pairs whose views overlap — co-visibility
is measured with the depth maps (`covisibility`), so a pair's relative pose is observable from the images.

Used by perf/real_pairs.py (solved fraction per backend), perf/place_recognition.py (true revisits) and the
RGB-D coarse-guess tests. A pair (i, j) means query = frame i, match = frame j, T_query_match = T_wi^-1 T_wj.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

ROT_BINS = ((5.0, 15.0), (15.0, 30.0), (30.0, 60.0))  # degrees, the bins
SOLVED_ROT_DEG, SOLVED_DIR_DEG = 5.0, 15.0


def covisibility(depth_q: np.ndarray, depth_m: np.ndarray, T_query_match: np.ndarray, camera: PinholeCamera, *,
                 stride: int = 8, rel_tol: float = 0.05) -> float:
    """Fraction of the query's valid-depth pixels (every `stride`-th) seen by the match camera at the same depth.

    depth_*: [H, W] metres, 0 = invalid. A query point is seen when it projects inside the match image in front
    of the camera and the match depth there agrees within `rel_tol` (relative), i.e. it is not occluded.
    """
    v, u = np.mgrid[0 : camera.height : stride, 0 : camera.width : stride]
    z = depth_q[v, u]
    ok = z > 0
    if not ok.any():
        return 0.0
    u, v, z = u[ok], v[ok], z[ok]
    p_q = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], 1)
    T_m_q = se3.inverse(T_query_match)
    p_m = p_q @ T_m_q[:3, :3].T + T_m_q[:3, 3]
    front = p_m[:, 2] > 1e-3
    um = camera.fx * p_m[:, 0] / np.where(front, p_m[:, 2], 1) + camera.cx
    vm = camera.fy * p_m[:, 1] / np.where(front, p_m[:, 2], 1) + camera.cy
    inside = front & (um >= 0) & (um <= camera.width - 1) & (vm >= 0) & (vm <= camera.height - 1)
    seen = np.zeros(len(z), bool)
    ui, vi = np.rint(um[inside]).astype(int), np.rint(vm[inside]).astype(int)
    zm = depth_m[vi, ui]
    seen[inside] = (zm > 0) & (np.abs(zm - p_m[inside, 2]) < rel_tol * p_m[inside, 2])
    return float(seen.mean())


def load_sequence(path):
    """The Redwood sequence at `path` (slam.io.datasets loader), with its poses checked to be present."""
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.datasets import load_sequence as _load

    seq = _load(path)
    if seq.gt_poses is None or not np.isfinite(seq.gt_poses).all():
        raise InputError(f"{path}: needs a trajectory.log with a pose for every frame")
    return seq


def rotation_angles(poses: np.ndarray) -> np.ndarray:
    """[N, 4, 4] T_world_cam -> [N, N] rotation angle between every two cameras, degrees."""
    R = poses[:, :3, :3]
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0  # trace(R_i^T R_j) = sum of elementwise products
    return np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)))


def sample_pairs(seq, *, per_bin: int = 30, bins=ROT_BINS, min_covis: float = 0.3, seed: int = 0,
                 max_tries: int = 4000) -> list[dict]:
    """Up to `per_bin` frame pairs per rotation bin whose co-visibility is at least `min_covis`.

    -> [{"i", "j", "rot_deg", "dist_m", "covis", "bin"}], deterministic for a seed. Candidate pairs are drawn
    uniformly per bin; the depth test is run only on drawn pairs (at most `max_tries` per bin).
    """
    poses = seq.gt_poses
    ang = rotation_angles(poses)
    iu, ju = np.triu_indices(len(poses), 1)
    rng = np.random.default_rng(seed)
    depth_cache: dict[int, np.ndarray] = {}

    def depth(k):
        if k not in depth_cache:
            depth_cache[k] = seq[k].depth
        return depth_cache[k]

    out = []
    for b, (lo, hi) in enumerate(bins):
        a = ang[iu, ju]
        cand = np.flatnonzero((a >= lo) & (a < hi))
        rng.shuffle(cand)
        got = 0
        for c in cand[:max_tries]:
            i, j = int(iu[c]), int(ju[c])
            if rng.random() < 0.5:
                i, j = j, i  # either frame may be the query
            T = se3.inverse(poses[i]) @ poses[j]
            cv = min(covisibility(depth(i), depth(j), T, seq.camera), covisibility(depth(j), depth(i),
                                                                                 se3.inverse(T), seq.camera))
            if cv >= min_covis:
                out.append({"i": i, "j": j, "rot_deg": float(ang[i, j]), "dist_m": float(np.linalg.norm(T[:3, 3])),
                            "covis": cv, "bin": f"{lo:g}-{hi:g}"})
                got += 1
                if got == per_bin:
                    break
    return out


def is_solved(result, T_query_match: np.ndarray) -> bool:
    """Solved = registration succeeded, rotation error < 5 deg and translation direction error < 15 deg."""
    from swarmsplat.registration.pair.base import direction_error_deg, rotation_error_deg

    if not result.success:
        return False
    rot = rotation_error_deg(result.R, T_query_match[:3, :3])
    dire = direction_error_deg(result.t, T_query_match[:3, 3])
    return bool(rot < SOLVED_ROT_DEG and np.isfinite(dire) and dire < SOLVED_DIR_DEG)
