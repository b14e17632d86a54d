"""`swarmsplat pairs`: place recognition and pair registration over a multi-agent dataset, every candidate to CSV.

Steps (FLOCC-SLAM §III-A/B): describe every keyframe; for each keyframe of each agent and each other agent, its
nearest neighbour(s) among that agent's keyframes by cosine similarity above a threshold (0.1 in the paper);
register each candidate and the query's odometry pair; ratio, gate and confidence; compare with ground truth
where it exists. An unordered keyframe pair found from both sides is registered once, from the first agent.
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_write_text, output_file
from swarmsplat.registration.pair.base import direction_error_deg, rotation_error_deg
from swarmsplat.slam.config import PairsConfig, SlamConfig, with_section
from swarmsplat.slam.io.jsonio import write_json
from swarmsplat.slam.run.guard import SkipLog, guarded, keep, read_frame

COLUMNS = [
    "query_agent", "query_index", "query_time", "match_agent", "match_index", "match_time", "similarity",
    "success", "accepted", "reason", "n_matches", "n_correspondences", "odom_pair", "n_odom", "ratio", "p",
    "tx", "ty", "tz", "qx", "qy", "qz", "qw",
    "gt_distance_m", "rot_err_deg", "t_dir_err_deg", "t_err_m_gt_scale",
]


@dataclass
class PairsSummary:
    out: Path
    n_keyframes: int
    n_candidates: int
    n_registered: int
    n_accepted: int
    n_gt_inliers: int | None  # accepted loops within the paper's 2 m after GT scaling (None without GT)
    descriptor_bytes: int
    mean_encoding_bytes: float
    average_precision: dict  # score name -> AP of the inlier detector (Fig. 3), with ground truth
    skipped_frames: list = field(default_factory=list)  # {"agent", "frame", "reason"} of unreadable keyframes

    def line(self) -> str:
        gt = "" if self.n_gt_inliers is None else f", {self.n_gt_inliers} within 2 m of ground truth"
        ap = "".join(f", AP[{k}] {v:.3f}" for k, v in self.average_precision.items() if v == v)
        sk = f", {len(self.skipped_frames)} unreadable skipped" if self.skipped_frames else ""
        return (f"{self.n_keyframes} keyframes{sk}, {self.n_candidates} candidates, {self.n_registered} registered, "
                f"{self.n_accepted} accepted{gt}{ap}; descriptor {self.descriptor_bytes} B, encoding "
                f"{self.mean_encoding_bytes:.0f} B per keyframe -> {self.out}")


def config_path(out: str | Path) -> Path:
    """The config tree the run used, beside the candidates CSV (pairs.csv -> pairs.config.yaml)."""
    out = Path(out)
    return out.with_name(out.stem + ".config.yaml")


def metrics_path(out: str | Path) -> Path:
    """The JSON beside the candidates CSV: status, counts and skipped_frames (pairs.csv -> pairs.metrics.json)."""
    out = Path(out)
    return out.with_name(out.stem + ".metrics.json")


def gt_errors(T_est: np.ndarray, T_gt: np.ndarray) -> dict:
    """Errors of a unit-translation estimate against ground truth T_query_match: rotation (deg), translation
    direction (deg), and translation error in metres after scaling the estimate to the true length (Fig. 3)."""
    d = float(np.linalg.norm(T_gt[:3, 3]))
    t_scaled = T_est[:3, 3] * d
    return {"gt_distance_m": d, "rot_err_deg": rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
            "t_dir_err_deg": direction_error_deg(T_est[:3, 3], T_gt[:3, 3]) if d > 1e-6 else float("nan"),
            "t_err_m_gt_scale": float(np.linalg.norm(t_scaled - T_gt[:3, 3]))}


@guarded("pairs")
def run_pairs(dataset: str | Path, out: str | Path, config: SlamConfig | PairsConfig | None = None, *,
              vocabulary_out: str | None = None, trust_checkpoint: bool = False, progress: bool = True,
              **options) -> PairsSummary:
    """Run the front-end over `dataset` and write one CSV row per candidate to `out` (atomically), the run's
    status, counts and skipped keyframes to `metrics_path(out)`, and the config tree used to `config_path(out)`.

    config: the tree (or its pairs section); options: PairsConfig fields overriding it —
    backend: pair registration (classical | xfeat | mast3r | lightglue); checkpoint: its weights (mast3r).
    place: bow | vlad | xfeat-vlad | cosplace | netvlad; place_checkpoint: its weights (or a vocabulary .npz). Without a
        vocabulary, one is trained on the dataset's keyframes (deterministic) and saved to `vocabulary_out` if given.
    threshold: cosine similarity threshold (None: every nearest neighbour); top_k: neighbours per keyframe;
    stride: use every stride-th frame as a keyframe. r_thr, k: the gate and logistic of eqs. (1)-(2).
    strict: stop at an unreadable keyframe image (default: leave it out with a warning). An interrupt or a failure
    writes the rows registered so far with status "interrupted" / "failed" and re-raises.
    trust_checkpoint: let the MASt3R loader unpickle more than tensors (only for files from a trusted source).
    """
    from swarmsplat.graph.confidence import K_DEFAULT
    from swarmsplat.registration.pair import make_registrar
    from swarmsplat.registration.place_recognition import VOCABULARY_BACKENDS, PlaceDatabase, make_recognizer
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.flocc.frontend import LoopFrontend
    from swarmsplat.slam.io.progress import bar as progress_bar

    cfg = with_section(config, "pairs", options)
    p = cfg.pairs
    backend, place, device, stride, strict, k = p.backend, p.place, p.device, p.stride, p.strict, p.k
    output_file(out, "--out")
    ds = load_dataset(dataset)
    if len(ds.agents) < 2:
        raise InputError(f"{dataset}: inter-robot pairs need at least two agents, found {len(ds.agents)}")
    names = [s.name for s in ds.agents]
    if len(set(names)) != len(names):
        raise InputError(f"{dataset}: agent names are not unique: {names}")
    seqs = dict(zip(names, ds.agents))
    kf = {a: list(range(0, len(s), stride)) for a, s in seqs.items()}  # keyframe index -> frame index
    extra = {"trust_checkpoint": True} if (trust_checkpoint and backend == "mast3r") else {}
    registrar = make_registrar(backend, checkpoint=p.checkpoint, device=device, **extra)  # fail fast (no weights, ...)

    def image_of(agent: str, i: int) -> np.ndarray:
        return seqs[agent][kf[agent][i]].color

    recognizer = make_recognizer(place, checkpoint=p.place_checkpoint, device=device)
    if place in VOCABULARY_BACKENDS and not recognizer.trained:
        every = [(a, i) for a in names for i in range(len(kf[a]))]
        pick = every[:: max(1, len(every) // 60)]  # up to ~60 training images, spread over all agents
        frames = [read_frame(seqs[a], kf[a][i], SkipLog(quiet=True), strict=strict) for a, i in pick]
        recognizer.fit([f.color for f in frames if f is not None], seed=0)
        if vocabulary_out:
            recognizer.save(vocabulary_out)

    db = PlaceDatabase(recognizer.dim)
    desc, skips, rows = {}, {a: SkipLog(a) for a in names}, []
    keep(lambda status, reason: _write_partial(out, rows, status, reason, skips))
    bar = progress_bar(sum(map(len, kf.values())), "[pairs] describe", unit="keyframe", enabled=progress)
    for a in names:
        described, readable = [], []
        for f_index in kf[a]:
            f = read_frame(seqs[a], f_index, skips[a], strict=strict)
            if f is not None:  # an unreadable keyframe is left out: the keyframe indices skip it
                described.append(recognizer.describe(f.color))
                readable.append(f_index)
            bar.update(1)
        if not readable:
            raise InputError(f"{dataset}: no keyframe image of agent {a} can be read")
        kf[a] = readable
        desc[a] = np.stack(described)
        db.add_many(a, range(len(kf[a])), desc[a])
    bar.close()

    seen, cands = set(), []
    for a in names:  # robot a searches each neighbour b's descriptors for every own keyframe, as when they meet
        for b in names:
            if b == a:
                continue
            for m in db.candidates(a, range(len(kf[a])), desc[a], threshold=p.threshold, k=p.top_k, agents=[b]):
                key = frozenset([(m.query_agent, m.query_index), (m.agent, m.index)])
                if key not in seen:
                    seen.add(key)
                    cands.append(m)

    front = LoopFrontend(registrar, image_of, lambda a: seqs[a].camera, lambda a: len(kf[a]),
                         k=K_DEFAULT if k is None else k, r_thr=p.r_thr)
    n_reg, n_acc, n_in = 0, 0, 0
    have_gt = all(s.gt_poses is not None for s in seqs.values())
    with progress_bar(len(cands), "[pairs] register", unit="pair", enabled=progress) as reg_bar:
        for m in cands:
            meas = front.evaluate((m.query_agent, m.query_index), (m.agent, m.index), m.similarity)
            n_reg += int(meas.loop.success)
            n_acc += int(meas.accepted)
            rows.append(_row(meas, seqs, kf, have_gt))
            if have_gt and meas.accepted and rows[-1]["t_err_m_gt_scale"] <= 2.0:
                n_in += 1
            reg_bar.update(1, f"{n_acc} accepted")
    _write_csv(out, rows)
    enc_bytes = [e.nbytes for e in front.encodings.values()]
    ap = {sc: inlier_precision_recall(rows, sc)["ap"] for sc in ("similarity", "n_correspondences", "ratio")} \
        if have_gt else {}
    summary = PairsSummary(Path(out), sum(map(len, kf.values())), len(cands), n_reg, n_acc,
                           n_in if have_gt else None, recognizer.descriptor_bytes,
                           float(np.mean(enc_bytes)) if enc_bytes else 0.0, ap,
                           [r for s in skips.values() for r in s.rows])
    write_json(metrics_path(out), {"status": "complete", **asdict(summary), "out": str(out)})
    atomic_write_text(config_path(out), cfg.to_yaml())
    return summary


def _write_partial(out, rows: list[dict], status: str, reason: str, skips: dict) -> Path:
    """The candidates registered before an interrupt or a failure, and their metrics JSON."""
    _write_csv(out, rows)
    write_json(metrics_path(out), {"status": status, "reason": reason, "n_rows": len(rows), "out": str(out),
                                   "skipped_frames": [r for s in skips.values() for r in s.rows]})
    return Path(out)


def inlier_precision_recall(rows: list[dict], score: str, *, outlier_m: float = 2.0) -> dict:
    """FLOCC Fig. 3: how well `score` (similarity | n_correspondences | ratio) separates inlier loops from outliers.

    rows: CSV rows (dicts) of registered candidates with ground truth; a loop is an outlier when its translation
    error after scaling with ground truth exceeds `outlier_m` metres (the paper's 2 m). Returns thresholds sorted
    by descending score with precision and recall at each, and the average precision (area under the PR steps).
    """
    data = [(float(r[score]), float(r["t_err_m_gt_scale"]) <= outlier_m) for r in rows
            if str(r.get("success")) == "1" and r.get("t_err_m_gt_scale", "") != "" and r.get(score, "") != ""]
    if not data:
        return {"score": score, "n": 0, "n_inliers": 0, "ap": float("nan"), "threshold": [], "precision": [],
                "recall": []}
    s = np.array([d[0] for d in data])
    y = np.array([d[1] for d in data], bool)
    order = np.argsort(-s, kind="stable")
    tp = np.cumsum(y[order])
    precision = tp / np.arange(1, len(s) + 1)
    recall = tp / max(int(y.sum()), 1)
    ap = float(np.sum(np.diff(np.r_[0.0, recall]) * precision))
    return {"score": score, "n": len(s), "n_inliers": int(y.sum()), "ap": ap, "threshold": s[order].tolist(),
            "precision": precision.tolist(), "recall": recall.tolist()}


def _row(meas, seqs, kf, have_gt: bool) -> dict:
    (qa, qi), (ma, mi) = meas.query, meas.match
    fq, fm = kf[qa][qi], kf[ma][mi]
    T = meas.T_query_match
    t, q_xyzw = se3.to_tum(T)
    row = {"query_agent": qa, "query_index": qi, "query_time": float(seqs[qa].timestamps[fq]), "match_agent": ma,
           "match_index": mi, "match_time": float(seqs[ma].timestamps[fm]), "similarity": meas.similarity,
           "success": int(meas.loop.success), "accepted": int(meas.accepted), "reason": meas.reason,
           "n_matches": meas.loop.n_matches, "n_correspondences": meas.loop.n_correspondences,
           "odom_pair": "" if meas.odom_pair is None else f"{meas.odom_pair[0]}-{meas.odom_pair[1]}",
           "n_odom": "" if meas.odom is None else meas.odom.n_correspondences,
           "ratio": "" if meas.ratio is None else meas.ratio, "p": "" if meas.p is None else meas.p,
           "tx": t[0], "ty": t[1], "tz": t[2], "qx": q_xyzw[0], "qy": q_xyzw[1], "qz": q_xyzw[2], "qw": q_xyzw[3]}
    if have_gt:
        T_gt = se3.inverse(seqs[qa].gt_poses[fq]) @ seqs[ma].gt_poses[fm]
        errs = gt_errors(T, T_gt)
        if not meas.loop.success:  # no estimate: keep the GT distance, leave the errors empty
            errs = {"gt_distance_m": errs["gt_distance_m"], "rot_err_deg": "", "t_dir_err_deg": "",
                    "t_err_m_gt_scale": ""}
        row.update(errs)
    return row


def _write_csv(out, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, restval="")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write_text(out, buf.getvalue())
