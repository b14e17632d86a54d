"""What a real-time run does around its stream (slam.run.realtime): the kernels loaded before the clock starts
(warmup), the mapping iterations real time cut short added to the final map refinement (runtime.refine_owed), and
what `python -m perf realtime` reports of both."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.mapping.refine_merged import iteration_budget

from test_run_guard import _config, _sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return _sequence(tmp_path_factory.mktemp("rt"), 12) / "agent_0"


def test_the_map_refinement_takes_the_mapping_iterations_real_time_cut_short():
    from swarmsplat.slam.run.realtime.run import owed_iterations, with_owed_iterations

    log = [{"planned": 100, "iterations": 7}, {"planned": 30, "iterations": 30}, {"planned": 30, "iterations": 5}]
    assert owed_iterations(log) == 93 + 25
    assert owed_iterations(log, 4, 30) == 93 + 25 + 4 * 30  # each late view: the iterations a keyframe is mapped with
    cfg = SlamConfig().override({"map_refine": {"iterations_per_keyframe": 16, "max_iterations": 1000}})
    assert iteration_budget(with_owed_iterations(cfg, 3, 118).map_refine, 3) == 3 * 16 + 118
    assert iteration_budget(with_owed_iterations(cfg, 100, 118).map_refine, 100) == 1000 + 118  # past the cap
    assert with_owed_iterations(cfg, 3, 0) is cfg
    off = cfg.override({"map_refine": {"iterations_per_keyframe": 0}})
    assert with_owed_iterations(off, 3, 118) is off  # a refinement turned off stays off


def test_perf_realtime_reads_the_offline_rows_counts_from_the_run(monkeypatch, tmp_path):
    """`python -m perf realtime`'s offline row: frames tracked and dropped as the run counted them (here 8 of 10
    tracked, one skipped as unusable, one lost), never a constant 100 % and 0."""
    from swarmsplat.perf import realtime as perf_realtime
    from swarmsplat.slam.run import sequence

    run = {"frames": 10, "frames_tracked": 8, "skipped_frames": [{"frame": 3, "reason": "unreadable"}],
           "ate_rmse": 0.01, "psnr_merged": 30.0, "keyframes": 3}
    monkeypatch.setattr(sequence, "run_sequence", lambda *a, **k: run)
    row = perf_realtime.measure(tmp_path, None, None)
    assert row["mode"] == "offline" and row["tracked_pct"] == 80.0 and row["frames_tracked"] == 8
    assert row["dropped"] == 1


def test_the_warm_up_runs_the_first_frames_and_never_stops_the_run(seq, tmp_path):
    """The throwaway agent reads the first frames; a frame it cannot read ends it early without an error (the
    run's own loop skips such a frame with its reason)."""
    from swarmsplat.slam.run.realtime.warmup import FRAMES, warm_up
    from swarmsplat.slam.run.sequence import open_sequence

    cfg = SlamConfig.from_yaml(_config(tmp_path))
    s, n = open_sequence(seq, cfg, None)
    read = []

    def frames(i):
        read.append(i)
        if i == 1:
            raise ValueError("corrupt frame")
        f = s[i]
        return f.color, f.depth

    assert warm_up(s.camera, cfg, frames, n) > 0 and read == [0, 1]
    read.clear()
    assert warm_up(s.camera, cfg, lambda i: read.append(i) or (s[i].color, s[i].depth), n) > 0
    assert read == list(range(FRAMES))


def test_perf_realtime_reports_the_warm_up_and_the_owed_refinement(monkeypatch, tmp_path):
    from swarmsplat.perf import realtime as perf_realtime
    from swarmsplat.slam.run.realtime import run as rt_run

    r = {"tracked_fraction": 0.9, "frames_tracked": 9, "frames_dropped": 1, "dropped_by_reason": {"stale": 1},
         "pose_latency_ms": {"p50": 1.0, "p95": 2.0, "max": 3.0}, "step_ms": {"p50": 1.0, "p95": 2.0},
         "ate_rmse_live": 0.01, "mapping_iterations": {"mean": 5.0}, "keyframes_deferred": 2, "stream_s": 1.0,
         "cpu_s": {"tracker_thread": 0.5, "mapping_thread": 0.5, "process": 1.5}, "warm_up_s": 1.25,
         "refine_owed_iterations": 77}
    run = {"frames": 10, "frames_tracked": 9, "ate_rmse": 0.01, "psnr_merged": 30.0, "keyframes": 3, "realtime": r,
           "time_s": {"map_refine": 12.5}}
    monkeypatch.setattr(rt_run, "run_realtime", lambda *a, **k: run)
    row = perf_realtime.measure(tmp_path, 15.0, None)
    assert (row["warm_up_s"], row["refine_owed_iterations"], row["map_refine_s"]) == (1.25, 77, 12.5)
    table = perf_realtime.markdown({"data": str(tmp_path), "rows": [row]})
    header = next(line for line in table.splitlines() if line.startswith("| mode") and "cpu_tracker_s" in line)
    assert header.endswith("| warm_up_s | refine_owed_iterations | map_refine_s |")
    assert "| 77 | 12.5 |" in table
