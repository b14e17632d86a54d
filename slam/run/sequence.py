"""Run one agent over one RGB-D sequence and write everything a user needs next to each other:
trajectory (TUM), Gaussian map (3DGS PLY), metrics.json, loops.csv, plots, and the config actually used."""

from __future__ import annotations

import csv
import io
import sys
import time
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_write_text, output_dir

from swarmsplat.slam.dense.agent import Agent
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.metrics.views import exposure_record, keyframe_metrics
from swarmsplat.slam.io.jsonio import write_json
from swarmsplat.slam.dense.loops.loop_log import count_by_source
from .partial_results import write_partial_agent
from swarmsplat.slam.run.guard import guarded, keep, read_frame
from .runtime import check_not_empty, guard_warnings, kernels_record

JOURNAL = Path("progress") / "poses.tum"  # slam.run.checkpoint.PoseJournal


@guarded("run")
def run_sequence(dataset_path: str | Path, out_dir: str | Path, config: SlamConfig | None = None, *,
                 frames: int | None = None, progress: bool = True,
                 observer=None, strict: bool = False, resume: bool = False) -> dict:
    """Track and map `dataset_path` (any layout `slam.io.datasets.load_sequence` reads) with one agent.

    frames: process at most this many (None: config.max_frames, 0 meaning all). Returns the metrics dict that is
    also written to `out_dir/metrics.json`. observer: called with the agent after every frame (slam.view.live).
    An unreadable frame is skipped with a warning (strict: the run stops with its error); an interrupt or a
    failure mid-run writes what was done so far (slam.run.guard, slam.run.partial_results) and re-raises.
    As it goes the run appends each keyframe's frames to out_dir/progress/poses.tum and writes checkpoints
    (config `checkpoint`; slam.run.checkpoint); resume: continue the run in `out_dir` from its last checkpoint
    (InputError naming what differs when it is not a run of this dataset and config).
    """
    from swarmsplat.slam.io.progress import bar
    from .checkpoint import CHECKPOINT, PoseJournal, find_resume, run_identity, save_checkpoint
    from .runtime import check_device, use_kernels

    cfg = config or SlamConfig()
    use_kernels(cfg.kernels)
    seq, n = open_sequence(dataset_path, cfg, frames)
    check_device(cfg.kernels, [seq.camera], cfg.image.max_width)
    out = output_dir(out_dir, "--out")
    identity = run_identity(seq, cfg, n)
    resumed = find_resume(out, identity) if resume else None
    atomic_write_text(out / "config.yaml", cfg.to_yaml())

    agent = resumed.agent if resumed else Agent(seq.camera, cfg, name=seq.name)
    offload(agent, out, cfg)
    start = resumed.next_frame if resumed else 0
    if resume and progress:
        print(f"[{seq.name}] resuming at frame {start} of {n}" if resumed else
              f"[{seq.name}] no checkpoint in {out} yet: starting from the first frame", file=sys.stderr)
    agent.keep_keyframe_images = refines(cfg) and cfg.map_refine.views == "mapping"  # the refinement's views
    journal = PoseJournal(out / JOURNAL, resume=resumed.journal if resumed else None)
    t0 = time.perf_counter() - (resumed.wall_s if resumed else 0.0)  # the run's time includes the work resumed
    keep(lambda status, reason: write_partial_agent(agent, out, status=status, reason=reason, n_frames=n,
                                                    wall_s=time.perf_counter() - t0))
    every = cfg.checkpoint.every_submaps

    def checkpoint(next_frame: int) -> None:
        save_checkpoint(out, identity, agent, next_frame=next_frame, journal=journal.state(),
                        wall_s=time.perf_counter() - t0)

    with journal, bar(n, f"[{seq.name}] frames", unit="frame", enabled=progress) as b:
        if start:
            b.update(start)
        for i in range(start, n):
            n_submaps = len(agent.gmap.submaps)
            f = read_frame(seq, i, agent, strict=strict)
            if f is not None:  # None: unreadable, skipped with a warning
                agent.step(f.index, f.timestamp, f.color, f.depth)
                journal.follow(agent)
            b.update(1, f"{len(agent.gmap)} Gaussians  {len(agent.gmap.submaps)} submaps")
            if observer is not None:
                observer(agent)
            finished = len(agent.gmap.submaps) - 1  # submaps finished (frozen) so far
            if every and len(agent.gmap.submaps) > n_submaps and finished and finished % every == 0:
                checkpoint(i + 1)
    if every and start < n:  # every frame done: a kill in the refinement resumes at the refinement
        checkpoint(n)
    metrics = finish_agent_run(agent, seq, out, cfg, n_frames=n, t0=t0, progress=progress)
    (out / CHECKPOINT).unlink(missing_ok=True)  # a complete run needs none; the journal stays
    return metrics


def open_sequence(dataset_path, cfg: SlamConfig, frames: int | None = None):
    """(the sequence at `dataset_path`, how many of its frames to run: `frames`, else config max_frames, 0 meaning
    all); a loaded sequence is taken as it is (e.g. the one agent of a dataset root holding a single sequence).
    InputError when there is no frame to run."""
    from swarmsplat.slam.io.datasets import load_sequence

    seq = load_sequence(dataset_path) if isinstance(dataset_path, (str, Path)) else dataset_path
    n = len(seq)
    limit = frames if frames is not None else cfg.max_frames
    if limit:
        n = min(n, int(limit))
    if n == 0:
        raise InputError(f"{seq.root}: the sequence has no frames")
    return seq, n


def offload(agent: Agent, out: Path, cfg: SlamConfig) -> None:
    """With config submaps.offload, the agent's finished submaps go to out/submaps/NNNN.bin; with
    submaps.offload_keyframes, their keyframes' packed images to out/keyframes/ (a resumed agent's files are looked
    for there, wherever the folder has moved)."""
    from swarmsplat.slam.dense.submap_codec import use_storage
    from swarmsplat.slam.io.submap_files import KeyframeFiles, SubmapFiles

    if isinstance(agent.gmap.store, SubmapFiles):
        agent.gmap.store.folder = (out / "submaps").resolve()
    elif cfg.submaps.offload:
        use_storage(agent.gmap, cfg.submaps.storage, SubmapFiles(out / "submaps"))
    if agent.frame_store is not None:
        agent.frame_store.folder = out / "keyframes"
    elif cfg.submaps.offload_keyframes and agent.compress_keyframes:
        agent.frame_store = KeyframeFiles(out / "keyframes")


def refines(cfg: SlamConfig) -> bool:
    """Whether a one-agent run refines its merged map after the last frame (config map_refine)."""
    rc = cfg.map_refine
    return rc.single_agent and rc.iterations_per_keyframe > 0 and rc.max_iterations > 0


def finish_agent_run(agent: Agent, seq, out: Path, cfg: SlamConfig, *, n_frames: int, t0: float, progress: bool,
                     extra: dict | None = None) -> dict:
    """After the last frame: score the submaps as mapped, refine the merged map (config map_refine), write the
    results (`write_results`, with `extra` added to the metrics). t0: perf_counter() at the run's start; the
    evaluation is not part of the run's time."""
    rc = cfg.map_refine
    refined = None
    # the mapping stage's own-submap scores, before the refinement fits the submaps jointly (slam.metrics.views)
    t_eval = time.perf_counter()
    own = keyframe_metrics(agent, seq, merged=False)
    t_eval = time.perf_counter() - t_eval  # evaluation is not part of the run's time
    before = None
    if refines(cfg):  # the merged map over all keyframes at their final poses (slam.dense.mapping.refine)
        from swarmsplat.slam.io.progress import reporting
        from swarmsplat.slam.dense.mapping.refine import refine_agent, refines_poses

        before = agent.trajectory(per_keyframe=True)[1] if refines_poses(rc, agent.keyframes) else None
        with reporting(progress):
            refined = refine_agent(agent, rc, cfg.mapping, cfg.exposure if agent.exposure_active else None)
    wall = time.perf_counter() - t0 - t_eval
    return write_results(agent, seq, out, wall_s=wall, n_frames=n_frames, map_refine=refined, own_scores=own,
                         trajectory_before_refine=before, extra=extra)


def write_results(agent: Agent, seq, out: Path, *, wall_s: float, n_frames: int,
                  map_refine: dict | None = None, own_scores: dict | None = None,
                  trajectory_before_refine: np.ndarray | None = None, extra: dict | None = None) -> dict:
    """Write the run's outputs and metrics.json; returns the metrics. trajectory_before_refine: the frames' poses
    before the map refinement refined the keyframe poses (its ATE is reported as ate_rmse_before_refine); extra:
    more metrics (a real-time run's `realtime`)."""
    from swarmsplat.slam.io.trajectory import write_tum

    from swarmsplat.slam.dense.ply import save_ply

    check_not_empty([agent])
    stamps, T_est = agent.trajectory(per_keyframe=True)
    _, T_no_lc = agent.trajectory_no_lc()
    if len(stamps):
        write_tum(out / "trajectory.txt", stamps, T_est)
        write_tum(out / "trajectory_no_lc.txt", stamps, T_no_lc)
    if agent.keyframes:  # keyframe poses in id order (loops.csv's query_kf / match_kf index them)
        write_tum(out / "keyframes.txt", np.array([k.timestamp for k in agent.keyframes]), agent.keyframe_world_poses())
    save_ply(out / "map.ply", agent.display_map(), max_color=None)
    _write_loops_csv(out / "loops.csv", agent.loops.log_rows())
    t = agent.time
    metrics = {
        "status": "complete",
        "agent": agent.name,
        "dataset": str(seq.root),
        "frames": n_frames,
        "frames_tracked": len(stamps),
        "skipped_frames": agent.skipped_frames(),
        "keyframes": len(agent.keyframes),
        "submaps": len(agent.gmap.submaps),
        "gaussians": len(agent.gmap),
        # frames whose coarse tracking failed and that recovery retried / placed (slam.dense.tracking.recovery)
        "tracking_recoveries": agent.tracker.recoveries.as_dict(),
        "loop_candidates": len(agent.loops.log),
        "loops_accepted": sum(1 for c in agent.loops.log if c.accepted),
        "pose_graph_optimisations": agent.loops.optimisations,
        "pose_graph_not_applied": agent.loops.not_applied,
        "loops_by_source": count_by_source(agent.loops.log),
        "verification_budget": agent.loops.budget(),
        "loops_cloud_route": agent.loops.cloud_stats(),
        "fps": n_frames / wall_s if wall_s > 0 else float("nan"),
        "time_s": {"total": wall_s, "tracking": t.tracking, "mapping": t.mapping, "loop_closure": t.loop_closure,
                   "map_refine": map_refine["seconds"] if map_refine else 0.0},
        "map_refine": map_refine,
        # the keyframes' exposure and white balance (slam.dense.mapping.exposure) and how renders are scored
        "exposure": {**exposure_record(agent.keyframes), "enabled": agent.cfg.exposure.enabled,
                     "model_from_keyframe": agent.exposure_from},
        "kernels": kernels_record(agent.cfg.kernels),
    }
    metrics.update(guard_warnings([agent]))
    metrics.update(_trajectory_metrics(seq, stamps, T_est, out))
    if metrics.get("ate_rmse") is not None:  # the same run's tracking-only trajectory, aligned the same way
        metrics["ate_rmse_no_lc"] = _trajectory_metrics(seq, stamps, T_no_lc, None)["ate_rmse"]
        if trajectory_before_refine is not None:
            metrics["ate_rmse_before_refine"] = _trajectory_metrics(seq, stamps, trajectory_before_refine,
                                                                    None)["ate_rmse"]
    # working and input resolution (slam.metrics.views); own-submap scores as given (taken before refinement)
    metrics.update(keyframe_metrics(agent, seq, own=own_scores is None))
    metrics.update(own_scores or {})
    metrics.update(extra or {})
    write_json(out / "metrics.json", metrics)
    return metrics


def _trajectory_metrics(seq, stamps: np.ndarray, T_est: np.ndarray, out: Path | None) -> dict:
    from swarmsplat.slam.metrics import ate
    from swarmsplat.slam.io.plots import plot_trajectories

    gt = seq.gt_poses
    if gt is None or len(stamps) == 0:
        return {"ate_rmse": None}
    ok = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
    align = "se3"
    try:
        res = ate(seq.timestamps[ok], gt[ok], stamps, T_est, align=align, max_diff=1e-3)
    except InputError:
        # Too few or collinear positions for a rigid alignment (very short runs): anchor at the first frame instead.
        align = "first_pose"
        g0 = gt[ok][int(np.argmin(np.abs(seq.timestamps[ok] - stamps[0])))]
        res = ate(seq.timestamps[ok], gt[ok], stamps, g0 @ np.linalg.inv(T_est[0]) @ T_est, align="none", max_diff=1e-3)
    if out is None:
        return {"ate_rmse": res.rmse}
    plot_trajectories(out / "trajectory.png", {seq.name: res.pairs.T_gt[:, :3, 3]},
                      {seq.name: res.T_est_aligned[:, :3, 3]}, errors={seq.name: res.errors},
                      title=f"{seq.name}: ATE RMSE {100 * res.rmse:.2f} cm")
    return {"ate_rmse": res.rmse, "ate": {**res.to_dict(), "align": align}}


def _write_loops_csv(path: Path, rows: list[dict]) -> None:
    cols = ["query_kf", "match_kf", "query_frame", "match_frame", "similarity", "accepted", "reason", "fitness",
            "inlier_rmse", "correction_m", "source", "overlap", "route", "render_covisible", "render_agree",
            "render_violate", "render_photometric"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols)
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k) for k in cols})
    atomic_write_text(path, buf.getvalue())
