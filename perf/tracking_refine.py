"""perf subject "tracking-refine": does the frame-to-model refinement (tracking.refine) help, and what does it cost?

One agent (loop closure off) runs N frames of a sequence per variant: coarse-only (the peer) and refinement
variants (tracking-section overrides), in the same process. Per variant: ATE (SE(3)-aligned, against the
sequence's trajectory), tracking wall and process-CPU time (total and per-frame median; CPU counts every
thread of the process) and their ratio to coarse-only, and per-frame diagnostics, all taken outside the timers:

- `rel_*`: error of the pose relative to the model view's pose (the last keyframe), against the ground truth's
  relative pose (mm / deg): accumulated drift cancels, so this says whether the refinement moved each frame
  toward or away from the truth (`toward` = fraction of refined frames whose relative error went down).
- `loss_*`: eq.-5 tracking loss of the frame against the model rendered at the coarse and at the final pose
  (colour L1 [0-1] and depth L1 [m] where alpha >= alpha_min): does the refinement lower the residual against
  the *frame*?
- `view_psnr_db`: sharpness of the model view: PSNR of the view rendered at the keyframe pose against the
  keyframe itself (alpha >= alpha_min), and `view_coverage`, the fraction of its pixels with alpha >= alpha_min.
- In coarse-only runs, `shadow_*` is the refinement computed from each coarse pose against the same model but
  not applied (what it would do to a map built from coarse poses).

    python -m perf.tracking_refine --data ../shared/data/redwood_livingroom1_211 --frames 60 --json out.json
    python -m perf tracking-refine --json out.json      # Redwood 211 (if present) + a generated sequence
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DESCRIPTION = "frame-to-model refinement vs coarse-only tracking: ATE, tracking time ratio, per-frame diagnostics"

REDWOOD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "redwood_livingroom1_211"

# name -> tracking-section overrides (on top of the defaults). "coarse" is the peer.
VARIANTS: dict[str, dict] = {
    "coarse": {"refine": False},
    "refine": {"refine": True},
}


def _rel_error(T_view: np.ndarray, T: np.ndarray, G_view: np.ndarray, G: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between the estimated and the true pose of a frame relative to the view's pose."""
    from swarmsplat.kernels import se3

    E = se3.inverse(se3.inverse(G_view) @ G) @ (se3.inverse(T_view) @ T)
    return 1e3 * float(np.linalg.norm(E[:3, 3])), float(np.degrees(se3.rotation_angle(E[:3, :3])))


def _loss(params, frame, T, alpha_min: float) -> tuple[float, float]:
    """(colour L1, depth L1 in m) of `frame` against the model rendered at T where alpha >= alpha_min."""
    import torch

    from swarmsplat.kernels import se3
    from swarmsplat.slam.dense.render import render

    with torch.no_grad():
        out = render(params, torch.as_tensor(se3.inverse(T), dtype=torch.float32), frame.camera)
    m = out.alpha >= alpha_min
    c = (out.color - frame.color_tensor()).abs().mean(-1)[m]
    d = frame.depth_tensor()
    md = m & (d > 0)
    return (float(c.mean()) if c.numel() else float("nan"),
            float((out.depth - d).abs()[md].mean()) if md.any() else float("nan"))


def _refine_camera(agent, f, width: int):
    """The camera of frame `f` as the tracker sees it at the refinement width."""
    return agent._prepare(f.index, f.color, f.depth).resized(width).camera


def _view_psnr(view, keyframe, alpha_min: float) -> float:
    from swarmsplat.slam.metrics.image import psnr

    m = view.depth > 0
    if not m.any():
        return float("nan")
    return psnr(view.color.astype(np.float32) / 255.0, keyframe.color.astype(np.float32) / 255.0, mask=m)


def measure(seq, overrides: dict, frames: int, *, mapping: dict | None = None, shadow: bool = True,
            diagnostics: bool = True, poses: bool = False, stride: int = 1) -> dict:
    """Run one agent over the first `frames` frames of `seq` with tracking `overrides`; see the module doc."""
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import _trajectory_metrics
    from swarmsplat.slam.run.guard import read_frame
    from swarmsplat.slam.run.runtime import use_kernels
    from swarmsplat.slam.dense.tracking.tracker import refine_against_view

    upd = {"loop_closure": {"enabled": False}, "tracking": overrides}
    if mapping:
        upd["mapping"] = mapping
    cfg = SlamConfig().override(upd)
    use_kernels(cfg.kernels)
    agent = Agent(seq.camera, cfg, name=seq.name)
    tr = agent.tracker
    tc = cfg.tracking
    shadow_cfg = tc.model_copy(update={"refine": True})
    gt = seq.gt_poses
    times, cpus, rows, seen = [], [], [], {}
    inner = tr.track

    def timed(frame, params):
        t0, c0 = time.perf_counter(), time.process_time()
        r = inner(frame, params)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        seen["frame"], seen["result"] = frame, r
        return r

    tr.track = timed
    indices = list(range(0, len(seq), stride))[:frames]  # stride k: every k-th frame, as the demo runs
    n = len(indices)
    kf_index, kf_frame, view_id = None, None, None
    t_start = time.perf_counter()
    for i in indices:
        f = read_frame(seq, i, agent, strict=True)
        n_kf = len(agent.keyframes)
        params = agent.gmap.active.params if agent.gmap.submaps else None
        has_map = diagnostics and params is not None and len(params) > 0 and kf_index is not None
        if has_map and not tc.refine:  # coarse-only: render the same view the refinement would use (untimed)
            tr.view_of(params, _refine_camera(agent, f, tc.refine_max_width))
        agent.step(f.index, f.timestamp, f.color, f.depth)
        row = {"frame": int(f.index), "keyframe": len(agent.keyframes) > n_kf}
        if poses and "result" in seen and seen["result"] is not None:
            res = seen["result"]
            row["coarse_ok"] = bool(res.coarse_ok)
            row["T_coarse"], row["T_final"] = res.T_local_cam_coarse.tolist(), res.T_local_cam.tolist()
            if tr._view is not None:
                row["T_view"] = tr._view[1].tolist()
            if gt is not None:
                row["G"] = gt[i].tolist()
        if has_map and tr._view is not None and tr._view[0] is params and gt is not None:
            T_view, v = tr._view[1], tr._view[2]
            res, frame = seen["result"], seen["frame"]
            fr = frame.resized(tc.refine_max_width)
            if id(v) != view_id:
                view_id = id(v)
                row["view_psnr_db"] = _view_psnr(v, kf_frame, tc.alpha_min)
                row["view_coverage"] = float(v.valid_fraction())
            row["rel_coarse"] = _rel_error(T_view, res.T_local_cam_coarse, gt[kf_index], gt[i])
            row["rel_final"] = _rel_error(T_view, res.T_local_cam, gt[kf_index], gt[i])
            row["iterations"] = res.iterations
            ri = res.refine
            if ri is not None:
                row["refine"] = {"accepted": ri.accepted, "reason": ri.reason, "coverage": ri.coverage,
                                 "correction_mm": 1e3 * ri.correction_m, "correction_deg": ri.correction_deg,
                                 "score_ratio": ri.score_ratio,
                                 "inliers": [None if x is None else x.inlier_fraction for x in (ri.start, ri.final)],
                                 "photo": [None if x is None else x.photo_cost / max(x.photo_count, 1)
                                           for x in (ri.start, ri.final)],
                                 "geo": [None if x is None else x.cost / max(x.count, 1) for x in (ri.start, ri.final)]}
            row["loss_coarse"] = _loss(params, fr, res.T_local_cam_coarse, tc.alpha_min)
            if res.iterations:
                row["loss_final"] = _loss(params, fr, res.T_local_cam, tc.alpha_min)
            if shadow and not tc.refine:
                Ts, it, _ = refine_against_view(frame, v, T_view, res.T_local_cam_coarse, shadow_cfg,
                                                max_depth=cfg.image.max_depth)
                if it:
                    row["rel_shadow"] = _rel_error(T_view, Ts, gt[kf_index], gt[i])
                    row["loss_shadow"] = _loss(params, fr, Ts, tc.alpha_min)
        rows.append(row)
        if row["keyframe"]:
            kf_index, kf_frame = i, seen["frame"].resized(tc.refine_max_width)
    wall = time.perf_counter() - t_start
    stamps, T_est = agent.trajectory_no_lc()
    ate = _trajectory_metrics(seq, stamps, T_est, None)["ate_rmse"]
    return {"overrides": overrides, "frames": n, "stride": stride, "ate_mm": None if ate is None else 1e3 * ate,
            "tracking_s": float(sum(times)), "tracking_cpu_s": float(sum(cpus)),
            "tracking_ms_median": 1e3 * statistics.median(times[1:] or times),
            "mapping_s": agent.time.mapping, "wall_s": wall, "keyframes": len(agent.keyframes),
            "gaussians": len(agent.gmap), "summary": summarise(rows), "per_frame": rows,
            "view_bias_mm": [None if b is None else 1e3 * b for b in tr.view_biases],
            **({"T_est_no_lc": np.asarray(T_est).tolist()} if poses else {})}


def summarise(rows: list[dict]) -> dict:
    """Medians / fractions of the per-frame diagnostics (see the module doc)."""
    def med(key, j=0):
        v = [r[key][j] if isinstance(r[key], (list, tuple)) else r[key] for r in rows if key in r]
        v = [x for x in v if x == x]
        return float(statistics.median(v)) if v else None

    out = {k: med(k) for k in ("view_psnr_db", "view_coverage")}
    for k in ("rel_coarse", "rel_final", "rel_shadow", "loss_coarse", "loss_final", "loss_shadow"):
        out[f"{k}_0"], out[f"{k}_1"] = med(k, 0), med(k, 1)
    for other in ("final", "shadow"):
        pairs = [(r["rel_coarse"][0], r[f"rel_{other}"][0]) for r in rows
                 if f"rel_{other}" in r and (other == "shadow" or r.get("iterations"))]
        if pairs:
            out[f"toward_{other}"] = sum(b < a for a, b in pairs) / len(pairs)
            out[f"refined_frames_{other}"] = len(pairs)
            lp = [(r["loss_coarse"][1], r[f"loss_{other}"][1]) for r in rows if f"loss_{other}" in r]
            out[f"depth_loss_lower_{other}"] = sum(b < a for a, b in lp) / len(lp) if lp else None
    return out


def generated(root: Path, frames: int, width: int = 320, seed: int = 0) -> Path:
    """One agent of the demo's default preset (noise on) at width x 3/4 width, `frames` frames."""
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    cfg = GeneratorConfig.preset("default", agents=1, frames=frames, width=width, height=width * 3 // 4, seed=seed)
    return generate(root / f"gen_{width}_{frames}", cfg) / "agent_0"


def compare(seq, variants: dict[str, dict], frames: int, **kw) -> list[dict]:
    rows = []
    base = None
    for name, ov in variants.items():
        r = measure(seq, ov, frames, **kw)
        r["variant"], r["data"] = name, seq.name
        if base is None:
            base = r
        r["ratio_tracking"] = r["tracking_s"] / base["tracking_s"]
        r["ratio_tracking_cpu"] = r["tracking_cpu_s"] / base["tracking_cpu_s"]
        r["load"] = os.getloadavg()
        s = r["summary"]
        vb = [b for b in r["view_bias_mm"] if b is not None]
        s["view_bias_mm_median"] = float(statistics.median(vb)) if vb else None
        print(f"[{seq.name}] {name}: view bias median {s['view_bias_mm_median']} mm", file=sys.stderr)
        print(f"[{seq.name}] {name}: ATE {r['ate_mm']:.2f} mm  tracking {r['tracking_s']:.1f} s "
              f"({r['ratio_tracking']:.2f}x, cpu {r['ratio_tracking_cpu']:.2f}x)  rel coarse/final/shadow "
              f"{s['rel_coarse_0']}/{s['rel_final_0']}/{s['rel_shadow_0']} mm  toward {s.get('toward_final')}"
              f"/{s.get('toward_shadow')}  psnr {s['view_psnr_db']}  load {r['load'][0]:.1f}", file=sys.stderr)
        rows.append(r)
    return rows


COLUMNS = ["data", "variant", "frames", "ate_mm", "tracking_s", "tracking_cpu_s", "ratio_tracking",
           "ratio_tracking_cpu", "tracking_ms_median", "mapping_s", "load"]


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from swarmsplat.slam.io.datasets import load_sequence

    frames = 20 if quick else 60
    rows = []
    with tempfile.TemporaryDirectory(prefix="perf_refine_") as tmp:
        seqs = [load_sequence(generated(Path(tmp), frames))]
        if REDWOOD.is_dir():
            seqs.insert(0, load_sequence(REDWOOD))
        for seq in seqs:
            rows += compare(seq, VARIANTS, frames)
    flat = [{k: r[k] for k in COLUMNS} | {"summary": r["summary"]} for r in rows]
    return {"rows": flat, "columns": COLUMNS, "notes": [
        "Loop closure off; one process; coarse is the peer of every ratio. CPU time counts all threads; load = "
        "os.getloadavg() after the variant.", __doc__.split("\n\n")[1]]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.tracking_refine", description=DESCRIPTION)
    p.add_argument("--data", help="sequence folder (default: a generated one)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--variants", default="coarse,refine", help="comma-separated names of VARIANTS")
    p.add_argument("--set", action="append", default=[], metavar="NAME=JSON",
                   help="extra variant: tracking overrides as JSON, e.g. 'fine={\"iterations\": 3}'")
    p.add_argument("--mapping", default=None, help="mapping overrides as JSON (e.g. fewer iterations)")
    p.add_argument("--stride", type=int, default=1, help="use every k-th frame (the demo uses 2)")
    p.add_argument("--no-shadow", action="store_true")
    p.add_argument("--poses", action="store_true", help="store each frame's coarse / final / view pose and its "
                   "ground truth in the per-frame rows")
    p.add_argument("--json", dest="json_out")
    a = p.parse_args(argv)
    if a.stride < 1 or a.frames < 1:
        p.error(f"--stride and --frames: expected positive integers, got {a.stride} and {a.frames}")
    from swarmsplat.slam.io.datasets import load_sequence

    variants = {k: VARIANTS[k] for k in a.variants.split(",") if k}
    for s in a.set:
        name, js = s.split("=", 1)
        variants[name] = json.loads(js)
    with tempfile.TemporaryDirectory(prefix="perf_refine_") as tmp:
        seq = load_sequence(a.data) if a.data else load_sequence(generated(Path(tmp), a.frames))
        rows = compare(seq, variants, a.frames, mapping=json.loads(a.mapping) if a.mapping else None,
                       shadow=not a.no_shadow, poses=a.poses, stride=a.stride)
    if a.json_out:
        from .common import write_results

        write_results(a.json_out, None, {"rows": rows, "argv": argv or sys.argv[1:]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
