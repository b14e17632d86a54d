"""Place-recognition recall of true revisits per descriptor, each at the resolution the dense pipeline gives it.

Vocabularies (bow, vlad, xfeat-vlad) are trained (seed 0) on the very keyframes searched — what a team can do with
its own keyframes, no download. Descriptors see what the pipeline hands them: the agent's 160-pixel loop-closure
copy (`thumbnail@160`, the agent's descriptor) or the 320-pixel working copy the team server encodes for its
learned coarse start (`xfeat-vlad@320` reuses those encodings).

Data sets:
- real: Redwood livingroom1 (211 frames, 640x480), a keyframe every 3rd frame; intra-sequence search as an
  agent's loop detector runs it (keyframes within 50 frames of the query excluded).
- generated dense team: the demo's world (3 agents x 120 RGB-D frames, 320x240), a keyframe every 4th frame;
  inter-agent search (other agents' keyframes only), as the team server runs it.
- generated monocular team: the FLOCC Fig. 5 world (4 robots), inter-robot search.

True revisits: `near` = < 0.5 m and < 30 deg apart (ground-truth poses); `seen` (generated RGB-D team) = a
keyframe that sees >= 50 % of the query's depth pixels (reprojected with the ground truth) from wherever it stands:
in the generated rooms a near pose often faces another wall (near revisits see a median 45 % of each other), while
`seen` is what registration needs. On Redwood every keyframe sees >= 40 % of every other (one small room): `seen`
would count nearly every keyframe there, so it is not reported.

recall@k = share of queries having a true revisit whose k most similar keyframes include one. `sim_true` /
`sim_other` = median similarity of a query's best true revisit / 95th percentile over non-revisits: a fixed
similarity gate between them would separate them; their values differ per descriptor, which is why the team
server verifies its top-k candidates instead of gating on a number (server.tau_sim null).
"""

from __future__ import annotations

import os
import time

import numpy as np

DESCRIPTION = "place recognition: recall@1/5 of true revisits (real Redwood + generated teams) per descriptor"
REVISIT_M, REVISIT_DEG, GAP_FRAMES, SEEN_OVERLAP = 0.5, 30.0, 50, 0.5
# (name, image width, vocabulary): "own" = trained on the searched keyframes, "generic" = the shipped one
RECOGNIZERS = (("thumbnail", 160, None), ("bow", 320, "own"), ("vlad", 320, "own"), ("xfeat-vlad", 160, "own"),
               ("xfeat-vlad", 320, "own"), ("xfeat-vlad", 160, "generic"), ("xfeat-vlad", 320, "generic"))


def revisit_truth(poses_q: np.ndarray, poses_db: np.ndarray) -> np.ndarray:
    """[Nq, 4, 4], [Nd, 4, 4] T_world_cam -> [Nq, Nd] bool: < REVISIT_M apart and < REVISIT_DEG of rotation."""
    d = np.linalg.norm(poses_q[:, None, :3, 3] - poses_db[None, :, :3, 3], axis=-1)
    cos = (np.einsum("iab,jab->ij", poses_q[:, :3, :3], poses_db[:, :3, :3]) - 1.0) / 2.0
    ang = np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)))
    return (d < REVISIT_M) & (ang < REVISIT_DEG)


def overlap_truth(frames: list, poses: np.ndarray) -> np.ndarray:
    """[N, N] view overlap (slam.dense.loops.loop_closure.view_overlap) of frame i's depth pixels in frame j."""
    from swarmsplat.kernels import se3
    from swarmsplat.slam.dense.loops.view_overlap import view_overlap

    n = len(frames)
    out = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i != j:
                out[i, j] = view_overlap(frames[i], frames[j], se3.inverse(poses[j]) @ poses[i])
    return out


def recall(sim: np.ndarray, truth: np.ndarray, allowed: np.ndarray, ks=(1, 5)) -> dict:
    """sim, truth, allowed: [Nq, Nd]. Queries = rows with an allowed true revisit. -> recall@k, similarity spread."""
    truth = truth & allowed
    q = np.flatnonzero(truth.any(1))
    out = {"queries": int(len(q))}
    if not len(q):
        return out | {f"recall@{k}": float("nan") for k in ks} | {"sim_true": float("nan"), "sim_other": float("nan")}
    s = np.where(allowed, sim, -np.inf)[q]
    order = np.argsort(-s, axis=1, kind="stable")
    for k in ks:
        out[f"recall@{k}"] = float(np.mean([truth[qi, order[r, :k]].any() for r, qi in enumerate(q)]))
    out["sim_true"] = float(np.median(np.where(truth[q], sim[q], -np.inf).max(1)))
    others = sim[allowed & ~truth]
    out["sim_other"] = float(np.percentile(others, 95)) if len(others) else float("nan")
    return out


def _describe_all(name: str, images: list[np.ndarray], vocabulary: str | None) -> tuple[np.ndarray, float, int]:
    """Build recogniser `name` (vocabulary "own": trained on `images`; "generic": the shipped one), describe all."""
    from swarmsplat.registration.place_recognition import GENERIC, make_recognizer

    rec = make_recognizer(name, checkpoint=GENERIC if vocabulary == "generic" else None)
    if vocabulary == "own":
        rec.fit(images, seed=0)
    t0 = time.perf_counter()
    desc = rec.describe_many(images)
    return desc, 1e3 * (time.perf_counter() - t0) / len(images), rec.descriptor_bytes


def _keyframes(seqs, step: int) -> tuple[dict, np.ndarray, np.ndarray, list]:
    """Every step-th frame of each sequence -> ({width: [RGB]}, poses [N, 4, 4], owner [N], small RGBDs)."""
    from swarmsplat.slam.dense.frames import make_rgbd

    views, poses, owner, small = {160: [], 320: []}, [], [], []
    for a, seq in enumerate(seqs):
        for i in range(0, len(seq), step):
            f = seq[i]
            r = make_rgbd(f.color, f.depth, seq.camera, min_depth=0.05, max_depth=10.0)
            for w in views:
                views[w].append(r.resized(w).color)
            small.append(r.resized(160))
            poses.append(f.T_world_cam_gt)
            owner.append(a)
    return views, np.stack(poses), np.array(owner), small


def _rows(data: str, views: dict, truths: dict, allowed: np.ndarray) -> list[dict]:
    rows = []
    for name, width, vocabulary in RECOGNIZERS:
        desc, ms, nbytes = _describe_all(name, views[width], vocabulary)
        sim = desc @ desc.T
        label = f"{name}@{width}" + (f" ({vocabulary})" if vocabulary else "")
        for kind, truth in truths.items():
            rows.append({"data": data, "revisit": kind, "recognizer": label,
                         **recall(sim, truth, allowed), "describe_ms": ms, "bytes": nbytes})
    return rows


def real_rows(path) -> list[dict]:
    from .redwood_pairs import load_sequence

    seq = load_sequence(path)
    views, poses, _, _ = _keyframes([seq], 3)
    frames = np.arange(0, len(seq), 3)
    allowed = np.abs(frames[:, None] - frames[None]) >= GAP_FRAMES
    return _rows(f"real {path.name} ({len(frames)} kf)", views, {"near": revisit_truth(poses, poses)}, allowed)


def dense_team_rows(quick: bool) -> list[dict]:
    import tempfile
    from pathlib import Path

    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    with tempfile.TemporaryDirectory() as tmp:
        root = generate(Path(tmp) / "team", GeneratorConfig.preset("default", frames=60 if quick else None))
        seqs = load_dataset(root).agents
        views, poses, owner, small = _keyframes(seqs, 4)
    seen = overlap_truth(small, poses) >= SEEN_OVERLAP
    allowed = owner[:, None] != owner[None]
    return _rows(f"generated dense team ({len(poses)} kf)", views, {"near": revisit_truth(poses, poses),
                                                                    "seen": seen}, allowed)


def mono_team_rows(quick: bool) -> list[dict]:
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
    import cv2

    views = {w: [cv2.resize(im, (w, im.shape[0] * w // im.shape[1]), interpolation=cv2.INTER_AREA)
                 if im.shape[1] > w else im for im in images] for w in (160, 320)}
    return _rows(f"generated mono team ({len(images)} kf)", views, {"near": revisit_truth(poses, poses)},
                 owner[:, None] != owner[None])


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .real_pairs import DATA

    load = os.getloadavg()[0]
    rows = real_rows(DATA) if DATA.is_dir() else []
    rows += dense_team_rows(quick)
    rows += mono_team_rows(quick)
    notes = [f"near revisit: < {REVISIT_M} m and < {REVISIT_DEG:g} deg apart; seen: >= {SEEN_OVERLAP:.0%} of the "
             f"query's depth pixels seen by the keyframe (ground truth); real: intra-sequence, keyframes "
             f"< {GAP_FRAMES} frames from the query excluded; generated: inter-agent only",
             "vocabularies (bow 256 words, vlad 32 x 128, xfeat-vlad 32 x 64): 'own' = trained on the searched "
             "keyframes, 'generic' = shipped with the package (generated worlds of other seeds only); name@W = the "
             "keyframe images W pixels wide",
             "sim_true: median over queries of the best true revisit's similarity; sim_other: 95th percentile over "
             "non-revisits",
             f"1-minute load average at start {load:.1f} on {os.cpu_count()} CPUs"]
    if not DATA.is_dir():
        notes.append(f"{DATA} not found: no real rows")
    return {"rows": rows, "notes": notes,
            "columns": ["data", "revisit", "recognizer", "queries", "recall@1", "recall@5", "sim_true", "sim_other",
                        "describe_ms", "bytes"]}
