"""A long mission: one agent on a generated 320x240 sequence that loops through its rooms several times, run as
`swarmsplat run` runs it (slam.run.sequence.run_sequence, defaults). Does the run's memory and time per frame stay
flat as the mission grows?

Reported: peak RSS at the middle frame, after the last frame and after the final map refinement (the kernel's
high-water mark of the process that runs the mission; the sequence is generated in a process of its own
first); frames per second over the first and the last tenth of the frames; loop-closure time (candidate search, registration and
pose-graph optimisation) per keyframe over the first and the last tenth of the keyframes; the refinement's time;
the disk used by the run folder. The peer is the first tenth: the ratios last / first are the figures to watch.
Full: 3,000 frames, five laps; --quick: 300 frames, two laps.
"""

from __future__ import annotations

import multiprocessing
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

DESCRIPTION = "long mission: peak RSS, frame rate and loop-closure time per keyframe over time, disk per run"


def _status_kb(key: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process; False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_mb() -> float:
    kb = _status_kb("VmHWM")
    if kb is None:
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(kb / 1024.0, 1)


def _refined_count(st: dict | None) -> int | None:
    """Gaussians the refinement started from: the map less what the overlap cull dropped."""
    if not st or "gaussians" not in st:
        return None
    return int(st["gaussians"]) - int(st.get("overlap_dropped", 0))


def _tenths(x: list[float]) -> tuple[list[float], list[float]]:
    k = max(1, len(x) // 10)
    return x[:k], x[-k:]


def _disk_mb(path: Path) -> float:
    return round(sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20, 2)


def _generate(path: str, frames: int, laps: float) -> None:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate
    from swarmsplat.slam.synthetic.config import MotionConfig

    generate(Path(path), GeneratorConfig.preset("default", agents=1, frames=frames,
                                                motion=MotionConfig(loop_turns=laps)))


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.run.sequence import run_sequence

    frames, laps = (300, 2.0) if quick else (3000, 5.0)
    tmp = Path(tempfile.mkdtemp(prefix="perf-long-run-"))
    t0 = time.perf_counter()
    # generated in a process of its own: the generator's memory (hundreds of MB the allocator keeps) is not the
    # mission's, and a robot's process reads its frames from a sensor
    child = multiprocessing.get_context("spawn").Process(target=_generate, args=(str(tmp / "data"), frames, laps))
    child.start()
    child.join()
    if child.exitcode != 0:
        raise RuntimeError(f"generating the long-run sequence in {tmp / 'data'} failed (exit {child.exitcode})")
    seq = load_sequence(tmp / "data" / "agent_0")
    t_gen = time.perf_counter() - t0
    cfg = SlamConfig().override({"kernels": {"backend": backends[0], "device": device}})
    peak_reset = _reset_peak()

    frame_s: list[float] = []
    kf_loop_s: list[float] = []
    state = {"t": None, "kfs": 0, "loop": 0.0, "peak_mid": None}

    def observe(agent) -> None:
        now = time.perf_counter()
        if state["t"] is not None:
            frame_s.append(now - state["t"])
        state["t"] = now
        if len(agent.keyframes) > state["kfs"]:
            kf_loop_s.append(agent.time.loop_closure - state["loop"])
            state["kfs"], state["loop"] = len(agent.keyframes), agent.time.loop_closure
        if len(frame_s) == frames // 2:
            state["peak_mid"] = _peak_mb()
        if len(frame_s) == frames - 1:
            state["peak_frames"] = _peak_mb()
            state["t_frames"] = now

    out = tmp / "run"
    t0 = time.perf_counter()
    m = run_sequence(seq, out, cfg, progress=False, observer=observe)
    wall = time.perf_counter() - t0
    peak_end = _peak_mb()
    first, last = _tenths(frame_s)
    kf_first, kf_last = _tenths(kf_loop_s)
    fps_first, fps_last = len(first) / sum(first), len(last) / sum(last)
    lc_first, lc_last = 1e3 * float(np.mean(kf_first)), 1e3 * float(np.mean(kf_last))
    refine_s = time.perf_counter() - t0 - (state.get("t_frames", t0) - t0)
    row = {"frames": frames, "laps": laps, "keyframes": m.get("keyframes"), "submaps": m.get("submaps"),
           "loops_accepted": m.get("loops_accepted"), "gaussians": m.get("gaussians"),
           "peak_rss_mid_mb": state["peak_mid"], "peak_rss_frames_mb": state.get("peak_frames"),
           "peak_rss_end_mb": peak_end,
           "fps_first_tenth": round(fps_first, 2), "fps_last_tenth": round(fps_last, 2),
           "fps_last_over_first": round(fps_last / fps_first, 3),
           "loop_ms_per_kf_first_tenth": round(lc_first, 1), "loop_ms_per_kf_last_tenth": round(lc_last, 1),
           "loop_last_over_first": round(lc_last / lc_first, 3) if lc_first > 0 else None,
           "refine_and_write_s": round(refine_s, 1), "run_wall_s": round(wall, 1),
           "run_folder_mb": _disk_mb(out), "submaps_mb": _disk_mb(out / "submaps") if (out / "submaps").is_dir()
           else 0.0, "keyframes_mb": _disk_mb(out / "keyframes") if (out / "keyframes").is_dir() else 0.0,
           "ate_rmse_cm": round(100 * m["ate_rmse"], 2) if isinstance(m.get("ate_rmse"), (int, float)) else None,
           "psnr_merged_db": m.get("psnr_merged"),
           # the refinement: Gaussians after the overlap cull, and the most one region optimised at once
           "refine_regions": (m.get("map_refine") or {}).get("regions"),
           "refine_gaussians": _refined_count(m.get("map_refine")),
           "refine_region_gaussians_max": (m.get("map_refine") or {}).get("region_gaussians_max")}
    notes = [f"generated {frames} frames 320x240 ({laps:g} laps of a 2x2-room world) in {t_gen:.0f} s; "
             f"kernels {backends[0]} on {device}; defaults otherwise (finished submaps: submaps.storage "
             f"{cfg.submaps.storage}, offload {str(cfg.submaps.offload).lower()}; submaps_mb: their files; their "
             f"keyframes' images offloaded: {str(cfg.submaps.offload_keyframes).lower()}, keyframes_mb)",
             "peak RSS is the mission process's high-water mark from its first frame (the frames were generated in "
             "another process; VmHWM " + ("reset through /proc/self/clear_refs after the imports)" if peak_reset
                                          else "could not be reset: includes the imports)"),
             "loop closure per keyframe: candidate search, registration and pose-graph optimisation "
             "(Agent.time.loop_closure), averaged over the first and the last tenth of the keyframes"]
    return {"rows": [row], "columns": list(row), "notes": notes}
