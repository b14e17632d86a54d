"""Place-recognition recall of true revisits per descriptor: XFeat-VLAD beside thumbnail, BoW and RootSIFT-VLAD.

Two data sets, each vocabulary trained (seed 0) on the very keyframes it then searches — what a robot can do with
its own keyframes, no download:
- real: Redwood livingroom1 (211 frames, 640x480), a keyframe every 3rd frame. Intra-sequence search, as the
  dense agent's loop detector runs: keyframes within 50 frames of the query are excluded. A true revisit is a
  keyframe < 0.5 m and < 30 deg from the query (pseudo ground truth poses).
- generated: the Fig. 5 monocular team (4 robots, generator layout 2, 320x240, a keyframe per 0.2 m of odometry).
  Inter-robot search (other robots' keyframes only), true revisit as above.

recall@k = share of queries having a true revisit whose k best-scoring keyframes include one. `above_tau` = share
of those queries whose best true revisit scores >= the cosine threshold tau_sim = 0.1 (paper §IV), i.e. would
become a candidate at all. Times are per describe (wall, scales with the load) and the descriptor's bytes.
"""

from __future__ import annotations

import os
import time

import numpy as np

DESCRIPTION = "place recognition: recall@1/5 of true revisits (real Redwood + generated team) per descriptor"
REVISIT_M, REVISIT_DEG, GAP_FRAMES, TAU = 0.5, 30.0, 50, 0.1
RECOGNIZERS = ("thumbnail", "bow", "vlad", "xfeat-vlad")


def revisit_truth(poses_q: np.ndarray, poses_db: np.ndarray) -> np.ndarray:
    """[Nq, 4, 4], [Nd, 4, 4] T_world_cam -> [Nq, Nd] bool: < REVISIT_M apart and < REVISIT_DEG of rotation."""
    d = np.linalg.norm(poses_q[:, None, :3, 3] - poses_db[None, :, :3, 3], axis=-1)
    cos = (np.einsum("iab,jab->ij", poses_q[:, :3, :3], poses_db[:, :3, :3]) - 1.0) / 2.0
    ang = np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)))
    return (d < REVISIT_M) & (ang < REVISIT_DEG)


def recall(sim: np.ndarray, truth: np.ndarray, allowed: np.ndarray, ks=(1, 5)) -> dict:
    """sim, truth, allowed: [Nq, Nd]. Queries = rows with an allowed true revisit. -> recall@k, above_tau, n."""
    truth = truth & allowed
    q = np.flatnonzero(truth.any(1))
    out = {"queries": int(len(q))}
    if not len(q):
        return out | {f"recall@{k}": float("nan") for k in ks} | {"above_tau": float("nan")}
    s = np.where(allowed, sim, -np.inf)[q]
    order = np.argsort(-s, axis=1, kind="stable")
    for k in ks:
        out[f"recall@{k}"] = float(np.mean([truth[qi, order[r, :k]].any() for r, qi in enumerate(q)]))
    best_true = np.where(truth[q], sim[q], -np.inf).max(1)
    out["above_tau"] = float(np.mean(best_true >= TAU))
    return out


def _describe_all(name: str, images: list[np.ndarray]) -> tuple[np.ndarray, float, int]:
    """Build recogniser `name`, train it on `images` if it has a vocabulary, describe them all."""
    from swarmsplat.registration.place_recognition import VOCABULARY_BACKENDS, make_recognizer

    rec = make_recognizer(name)
    if name in VOCABULARY_BACKENDS:
        rec.fit(images, seed=0)
    t0 = time.perf_counter()
    desc = rec.describe_many(images)
    return desc, 1e3 * (time.perf_counter() - t0) / len(images), rec.descriptor_bytes


def real_rows(path, quick: bool) -> list[dict]:
    from .redwood_pairs import load_sequence

    seq = load_sequence(path)
    frames = np.arange(0, len(seq), 3)
    images = [seq[int(f)].color for f in frames]
    poses = seq.gt_poses[frames]
    truth = revisit_truth(poses, poses)
    allowed = np.abs(frames[:, None] - frames[None]) >= GAP_FRAMES
    rows = []
    for name in RECOGNIZERS:
        desc, ms, nbytes = _describe_all(name, images)
        rows.append({"data": f"real {path.name}", "recognizer": name, **recall(desc @ desc.T, truth, allowed),
                     "describe_ms": ms, "bytes": nbytes})
    return rows


def generated_rows(quick: bool) -> list[dict]:
    from .flocc_fig5 import StudyConfig
    from .flocc_fig5_data import Scene, keyframes

    cfg = StudyConfig.quick() if quick else StudyConfig()
    scene = Scene(cfg, seed=1)
    kf = {c: keyframes(scene.odometry[c], 0.2) for c in scene.robots}
    owner = np.array([c for c in scene.robots for _ in kf[c]])
    for c in scene.robots:
        scene.render(c, kf[c])
    images = [scene.image(c, f) for c in scene.robots for f in kf[c]]
    poses = np.stack([scene.gt[c][f] for c in scene.robots for f in kf[c]])
    truth = revisit_truth(poses, poses)
    allowed = owner[:, None] != owner[None]
    rows = []
    for name in RECOGNIZERS:
        desc, ms, nbytes = _describe_all(name, images)
        rows.append({"data": f"generated team ({len(images)} kf)", "recognizer": name,
                     **recall(desc @ desc.T, truth, allowed), "describe_ms": ms, "bytes": nbytes})
    return rows


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .real_pairs import DATA

    load = os.getloadavg()[0]
    rows = real_rows(DATA, quick) if DATA.is_dir() else []
    rows += generated_rows(quick)
    notes = [f"true revisit: < {REVISIT_M} m and < {REVISIT_DEG:g} deg apart; real: intra-sequence, keyframes "
             f"< {GAP_FRAMES} frames from the query excluded; generated: inter-robot only",
             "every vocabulary (bow 256 words, vlad 32 x 128, xfeat-vlad 32 x 64) trained on the searched keyframes",
             f"1-minute load average at start {load:.1f} on {os.cpu_count()} CPUs"]
    if not DATA.is_dir():
        notes.append(f"{DATA} not found: no real rows")
    return {"rows": rows, "notes": notes,
            "columns": ["data", "recognizer", "queries", "recall@1", "recall@5", "above_tau", "describe_ms", "bytes"]}
