"""Real-time mode (`swarmsplat run --realtime`, slam.run.realtime; its feed: test_realtime_feed.py): mapping on its
worker thread maps (and, given the time, maps exactly as the offline agent does); Ctrl-C stops both threads and
keeps every pose tracked; a bad --rate is one line. Latency itself is measured by `python -m perf realtime`, not
asserted here."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.mapping.refine_merged import iteration_budget

from test_run_guard import QUICK, _config, _sequence, _spawn, _stamps, interrupt_after


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return _sequence(tmp_path_factory.mktemp("rt"), 12) / "agent_0"


# ---- the agent on two threads --------------------------------------------------------------------------------------


def _frames(seq_path: Path, n: int):
    from swarmsplat.slam.io.datasets import load_sequence

    s = load_sequence(seq_path)
    return s, [s[i] for i in range(n)]


@pytest.mark.parametrize("exposure", ["auto", True])
def test_worker_maps_like_the_offline_agent_when_given_the_time(seq, exposure):
    """Stepping the real-time agent and letting its worker finish each keyframe before the next frame gives the
    offline agent's trajectory and map: the split over two threads changes when mapping runs, not what it does
    (across submaps too: the worker packs a retired submap's keyframe images and stores its Gaussians where the
    offline agent does both when it starts the next submap; and the worker fits each keyframe's exposure, which
    the offline agent does as it adds the keyframe). Each pose goes out before its keyframe is handed over, and a
    new submap started then leaves the emitted world pose as it was."""
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.dense.packed import PackedRGBD
    from swarmsplat.slam.run.realtime.agent import RealtimeAgent
    from swarmsplat.slam.run.runtime import use_kernels

    cfg = SlamConfig().override({**QUICK, "loop_closure": {"enabled": False}, "exposure": {"enabled": exposure},
                                 "submaps": {**QUICK["submaps"], "max_keyframes": 2}})
    use_kernels(cfg.kernels)
    s, frames = _frames(seq, 10)
    off = Agent(s.camera, cfg)
    rt = RealtimeAgent(s.camera, cfg)
    try:
        for f in frames:
            off.step(f.index, f.timestamp, f.color, f.depth)
            rec = rt.track(f.index, f.timestamp, f.color, f.depth)  # the pose goes out before the hand-over
            emitted = rt.gmap.submaps[rec.submap_id].T_world_local @ rec.T_local_cam
            rt.hand_over_keyframe()  # may start a submap: the record moves to its frame, the world pose stays
            np.testing.assert_allclose(rt.gmap.submaps[rec.submap_id].T_world_local @ rec.T_local_cam, emitted,
                                       atol=1e-9)
            assert rt._idle.wait(60)
        rt.finish(60)
    finally:
        rt.stop()
    assert len(rt.keyframes) == len(off.keyframes) >= 3 and len(rt.mapping_log) == len(rt.keyframes)
    assert len(rt.gmap.submaps) == len(off.gmap.submaps) >= 2
    assert all(type(a.small) is type(b.small) for a, b in zip(rt.keyframes, off.keyframes))  # packed alike
    assert any(isinstance(k.small, PackedRGBD) for k in rt.keyframes)
    assert [r["iterations"] for r in rt.mapping_log] == [r["planned"] for r in rt.mapping_log]  # none cut short
    np.testing.assert_allclose(rt.trajectory()[1], off.trajectory()[1], atol=1e-9)
    assert rt.exposure_active == off.exposure_active == (exposure is True or off.exposure_active)
    for k, o in zip(rt.keyframes, off.keyframes):
        assert (k.exposure is None) == (o.exposure is None) and k.exposure_outlier == o.exposure_outlier
        if k.exposure is not None:
            np.testing.assert_allclose(k.exposure, o.exposure, atol=1e-9)
            np.testing.assert_allclose(k.exposure_prior, o.exposure_prior, atol=1e-9)
    a, b = rt.gmap.merged(), off.gmap.merged()
    assert len(a) == len(b) > 0
    np.testing.assert_allclose(a.means.numpy(), b.means.numpy(), atol=1e-6)


def test_tracking_does_not_wait_for_mapping_and_stop_ends_the_worker(seq):
    """While the worker maps, frames are tracked against the map published before (keyframes due meanwhile are
    deferred and cut the mapping short); stop() ends a worker in the middle of a long optimisation within a
    second."""
    from swarmsplat.slam.run.realtime.agent import RealtimeAgent
    from swarmsplat.slam.run.runtime import use_kernels

    cfg = SlamConfig().override({**QUICK, "keyframes": {"every": 1},
                                 "runtime": {"min_mapping_iterations": 2, "max_mapping_iterations": 100000}})
    use_kernels(cfg.kernels)
    s, frames = _frames(seq, 4)
    rt = RealtimeAgent(s.camera, cfg)
    try:
        f = frames[0]
        rt.step(f.index, f.timestamp, f.color, f.depth)  # the first keyframe: 100000 iterations planned
        assert not rt.idle()
        if sys.platform.startswith("linux"):  # the worker runs at a lower priority than the tracker
            want = min(19, os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + cfg.runtime.mapping_nice)
            t0 = time.perf_counter()  # set by the worker as it starts
            while os.getpriority(os.PRIO_PROCESS, rt._thread.native_id) != want and time.perf_counter() - t0 < 5:
                time.sleep(0.01)
            assert os.getpriority(os.PRIO_PROCESS, rt._thread.native_id) == want
        f = frames[1]
        assert rt.step(f.index, f.timestamp, f.color, f.depth) is not None  # tracked meanwhile
        assert rt.keyframes_deferred == 1 and len(rt.keyframes) == 1  # due, deferred
        assert rt._idle.wait(60)  # the deferred keyframe cut the optimisation short
        assert 2 <= rt.mapping_log[0]["iterations"] < 100000
        for f in frames[2:]:
            rt.step(f.index, f.timestamp, f.color, f.depth)  # a keyframe again: the worker maps it, without end
        time.sleep(0.5)
        t0 = time.perf_counter()
        rt.stop(1.0)
        assert not rt._thread.is_alive() and time.perf_counter() - t0 < 1.0
    finally:
        rt.stop()
    assert len(rt.poses) == 4


def test_a_deferred_keyframe_is_kept_as_a_late_view_unless_its_keyframe_came_soon_after(seq):
    """runtime.late_views: the first frame deferred since the last keyframe is held; a keyframe within half of
    keyframes.every frames of it drops it (that keyframe sees nearly what it saw), a later one keeps it; a wait of
    keyframes.every frames keeps it and holds the frame deferred then; the end of the stream keeps the one held.
    Only when the refinement fits mapping-resolution views (keep_keyframe_images)."""
    from swarmsplat.slam.dense.submaps import start_submap
    from swarmsplat.slam.run.realtime.agent import RealtimeAgent

    cfg = SlamConfig().override({**QUICK, "keyframes": {"every": 4}})
    s, frames = _frames(seq, 1)
    rt = RealtimeAgent(s.camera, cfg)
    try:
        rt.keep_keyframe_images = True
        start_submap(rt.gmap, np.eye(4), rt.keyframes)
        frame = rt.prepare(frames[0])
        T = np.eye(4)

        def defer(i):
            rt._defer(i, 0.1 * i, frame, T)

        defer(10)
        rt._commit_late(11)  # the keyframe came 1 < 4 // 2 frames later: dropped
        assert rt.late_views == [] and rt._late is None
        defer(20)
        defer(21)  # the same wait: the candidate stays the first deferred frame
        rt._commit_late(23)  # 3 frames later: kept
        defer(30)
        defer(34)  # a wait of `every` frames: 30 kept, 34 held
        assert rt.late_views[0].map_rgbd is frame  # as tracked: resized after the stream, or packed on the worker
        rt.end_stream()
        assert [lv.frame_index for lv in rt.late_views] == [20, 30, 34]
        assert [lv.id for lv in rt.late_views] == [-1, -2, -3]  # never a keyframe's id
        lv = rt.late_views[0]
        assert lv.submap_id == rt.gmap.active.id and lv.map_rgbd is lv.small
        assert lv.map_rgbd.camera.width <= max(cfg.mapping.max_width, 1) or cfg.mapping.max_width <= 0
    finally:
        rt.stop()


def test_a_refinement_that_would_pass_the_deadline_is_left_out(seq):
    """A frame whose pose is already due is posed from the coarse stage alone (and counted), but never two frames
    in a row, so the refinement's time keeps being measured; without a deadline, or with
    runtime.skip_late_refinement off, the refinement runs as offline."""
    from swarmsplat.slam.run.realtime.agent import RealtimeAgent
    from swarmsplat.slam.run.runtime import use_kernels

    for skip in (True, False):
        cfg = SlamConfig().override({**QUICK, "loop_closure": {"enabled": False},
                                     "runtime": {"skip_late_refinement": skip}})
        use_kernels(cfg.kernels)
        s, frames = _frames(seq, 7)
        rt = RealtimeAgent(s.camera, cfg)
        try:
            for f in frames[:5]:
                rt.step(f.index, f.timestamp, f.color, f.depth)  # no deadline: refined, and timed
                assert rt._idle.wait(60)
            assert rt.tracker.refines_skipped == 0 and len(rt.tracker._refine_s) > 0
            n = len(rt.tracker._refine_s)
            for f in frames[5:]:  # both already late: the first goes without, the next refines (never twice)
                assert rt.track(f.index, f.timestamp, f.color, f.depth, deadline=time.monotonic() - 1.0) is not None
                rt.hand_over_keyframe()
            assert rt.tracker.refines_skipped == (1 if skip else 0) and rt.tracker.deadline is None
            assert len(rt.tracker._refine_s) == n + (1 if skip else 2)  # the refinement timed when it ran
        finally:
            rt.stop()


# ---- the command ---------------------------------------------------------------------------------------------------


def test_realtime_run_writes_what_it_measured(seq, tmp_path):
    from swarmsplat.slam.io.trajectory import read_tum
    from swarmsplat.slam.run.realtime.run import run_realtime

    out = tmp_path / "rt"
    emitted = []
    cfg = SlamConfig.from_yaml(_config(tmp_path)).override({"runtime": {"realtime": True, "rate": 15}})
    m = run_realtime(seq, out, cfg, progress=False, on_pose=lambda *a: emitted.append(a))
    r = m["realtime"]
    assert m["status"] == "complete" and r["rate_hz"] == 15 and r["frames"] == 12
    assert r["frames_tracked"] + r["frames_dropped"] + r["frames_skipped"] == 12
    assert sum(r["dropped_by_reason"].values()) == r["frames_dropped"]
    assert r["pose_latency_ms"]["count"] == r["frames_tracked"] == m["frames_tracked"] >= 1
    # every keyframe mapped, each for at least the iterations it is guaranteed and at most the ones planned
    its, rt = r["mapping_iterations"], cfg.runtime
    assert r["keyframes_mapped"] == m["keyframes"] == len(its["per_keyframe"]) >= 1
    assert rt.min_mapping_iterations <= its["min"] <= its["max"] <= cfg.mapping.first_iterations
    assert its["per_keyframe"][0] == cfg.mapping.first_iterations or its["cut_short"] >= 1
    # a map that renders its keyframes (against these frames a black image scores 9 dB, each frame's mean colour
    # 18 dB) and poses within a few cm of the truth (the scene is ~2 m across)
    assert m["gaussians"] > 0 and 20.0 < m["psnr"] < 60.0 and 20.0 < m["psnr_merged"] < 60.0, (m["psnr"], m["psnr_merged"])
    assert 0.0 < r["ate_rmse_live"] < 0.05 and r["ate_rmse_live"] == pytest.approx(m["ate_rmse"], rel=0.5, abs=0.01)
    stamps, _ = read_tum(out / "trajectory.txt")
    assert len(stamps) == r["frames_tracked"] == len(emitted)  # each tracked frame's pose, emitted as it came
    np.testing.assert_allclose([e[1] for e in emitted], stamps, atol=1e-6)
    assert all(e[2].shape == (4, 4) and e[3] > 0 for e in emitted)
    assert max(e[3] for e in emitted) * 1e3 == pytest.approx(r["pose_latency_ms"]["max"])
    report = (out / "report.md").read_text()
    assert "Pose latency" in report and f"{r['frames_tracked']} tracked" in report
    assert yaml_realtime(out)
    # the kernels were loaded before the stream; the refinement took its own budget and what mapping was cut short of
    assert r["warm_up_s"] > 0
    planned = [cfg.mapping.first_iterations] + [cfg.mapping.iterations] * (m["keyframes"] - 1)
    late = r["late_views"]
    if m["submaps"] == 1:
        assert r["refine_owed_iterations"] == (sum(max(0, p - i) for p, i in zip(planned, its["per_keyframe"]))
                                               + late * cfg.mapping.iterations)
    views = m["keyframes"] + late  # the late views are fitted as keyframes are, and are not held out
    assert m["map_refine"]["keyframes"] == views
    assert m["map_refine"]["iterations"] == iteration_budget(cfg.map_refine, views) + r["refine_owed_iterations"]
    assert late <= r["keyframes_deferred"] and m.get("late_views", 0) == late
    assert (m.get("psnr_late_views") is not None) == (late > 0)
    assert m["novel_views"] + m["keyframes"] + late <= m["frames_tracked"]



def test_late_views_are_fitted_by_the_refinement_and_scored_apart(seq, tmp_path):
    """A keyframe due at every frame and at least 20 mapping iterations each: at 30 Hz mapping cannot keep up, so
    keyframes are deferred and some are kept as late views. The final refinement fits them with the keyframes (and
    owes each the mapping iterations of a keyframe); metrics.json scores them apart (psnr_late_views) and never
    as held-out frames."""
    from swarmsplat.slam.run.realtime.run import run_realtime

    out = tmp_path / "rt"
    cfg = SlamConfig.from_yaml(_config(tmp_path)).override({"runtime": {"realtime": True, "rate": 30,
                                                                        "min_mapping_iterations": 20},
                                                            "keyframes": {"every": 1}})
    m = run_realtime(seq, out, cfg, progress=False)
    r = m["realtime"]
    late = r["late_views"]
    assert m["status"] == "complete" and 0 < late <= r["keyframes_deferred"], (late, r["keyframes_deferred"])
    assert m["late_views"] == late and m["map_refine"]["keyframes"] == m["keyframes"] + late
    assert r["refine_owed_iterations"] >= late * cfg.mapping.iterations
    assert 20.0 < m["psnr_late_views"] < 60.0 and 0.0 <= m["ssim_late_views"] <= 1.0
    tracked = m["frames_tracked"]
    assert m["novel_views"] == tracked - m["keyframes"] - late  # every other tracked frame is held out (<= 64)


def test_realtime_run_offloads_finished_submaps_as_an_offline_run_does(seq, tmp_path):
    """At 3 Hz, a keyframe every 2 frames and a submap every 2 keyframes: the worker writes each finished submap's
    Gaussians and its keyframes' images to the run folder. On an idle machine every frame is tracked in time; on a
    loaded one the first frames, which wait for the first mapping, may be dropped (2-3 of 12 at load 4-8, each
    with its reason). At load 4 and more, mapping also falls so far behind that keyframes are deferred and the
    run makes one submap: then this test fails, as real time on a shared machine does."""
    from swarmsplat.slam.run.realtime.run import run_realtime

    out = tmp_path / "rt"
    cfg = SlamConfig.from_yaml(_config(tmp_path)).override({"runtime": {"realtime": True, "rate": 3},
                                                            "keyframes": {"every": 2},
                                                            "submaps": {"max_keyframes": 2}})
    m = run_realtime(seq, out, cfg, progress=False)
    rt = m["realtime"]
    assert rt["frames_tracked"] + rt["frames_dropped"] == 12 and sum(rt["dropped_by_reason"].values()) == \
        rt["frames_dropped"] <= 3, json.dumps(rt, default=str)[:1500]
    assert m["frames_tracked"] == rt["frames_tracked"] and m["submaps"] >= 2
    assert len(list((out / "submaps").glob("*.bin"))) == m["submaps"] - 1
    kept = sorted(p.name for p in (out / "keyframes" / "small").glob("*.bin"))
    assert len(kept) >= 2 and len(kept) < m["keyframes"]  # the active submap's keyframes stay in memory


def test_too_slow_for_the_rate_completes_and_says_what_it_dropped(seq, tmp_path):
    """12 frames in 22 ms (500 Hz): the tracker cannot take them all; the run completes, and metrics.json and
    report.md give the drops by reason."""
    out = tmp_path / "fast"
    assert main(["run", str(seq), "--out", str(out), "--config", _config(tmp_path), "--realtime", "--rate", "500",
                 "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    r = m["realtime"]
    assert m["status"] == "complete" and r["frames_dropped"] >= 1 and r["frames_tracked"] >= 1
    assert r["frames_tracked"] + r["frames_dropped"] + r["frames_skipped"] == 12
    assert sorted(i for ids in r["dropped_frames"].values() for i in ids) == sorted(
        set(range(12)) - set(_tracked_indices(out, seq)))  # every frame not tracked was dropped
    report = (out / "report.md").read_text()
    assert "## Dropped frames" in report
    for reason, count in r["dropped_by_reason"].items():
        assert f"| {reason} | {count} |" in report


def _tracked_indices(out: Path, seq: Path) -> list[int]:
    from swarmsplat.slam.io.trajectory import read_tum

    stamps, _ = read_tum(out / "trajectory.txt")
    all_stamps = list(np.round(_stamps(seq), 6))
    return [all_stamps.index(round(float(t), 6)) for t in stamps]


def yaml_realtime(out: Path) -> bool:
    import yaml

    return yaml.safe_load((out / "config.yaml").read_text())["runtime"]["realtime"] is True


def test_offline_stays_the_default(seq, tmp_path):
    assert SlamConfig().runtime.realtime is False
    out = tmp_path / "off"
    assert main(["run", str(seq), "--out", str(out), "--config", _config(tmp_path), "--frames", "3",
                 "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert "realtime" not in m and m["frames_tracked"] == 3 and not (out / "report.md").exists()


@pytest.mark.parametrize("args, message", [
    (["--realtime", "--rate", "0"], "--rate must be a frame rate above 0 (Hz), got 0"),
    (["--realtime", "--rate", "-2"], "--rate must be a frame rate above 0 (Hz), got -2"),
    (["--realtime", "--rate", "nan"], "--rate must be a frame rate above 0 (Hz), got nan"),
    (["--realtime", "--rate", "fast"], "invalid float value: 'fast'"),
    (["--rate", "15"], "--rate sets the replay rate of real-time mode: give --realtime too"),
    (["--realtime", "--resume"], "--realtime does not take --resume"),
])
def test_bad_rate_is_one_line(seq, tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) if "fast" in args else _nothing():
        code = main(["run", str(seq), "--out", str(tmp_path / "x"), "--quiet", *args])
        assert code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and message in err[0], err


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_realtime_team_is_refused(tmp_path, capsys):
    data = _sequence(tmp_path / "team", 2, agents=2)
    assert main(["run", str(data), "--out", str(tmp_path / "x"), "--realtime", "--quiet"]) == 2
    assert "--realtime runs one agent" in capsys.readouterr().err


def test_sigint_stops_both_threads_and_keeps_the_poses(tmp_path):
    from swarmsplat.slam.io.trajectory import read_tum

    seq = _sequence(tmp_path / "data", 40) / "agent_0"
    out = tmp_path / "run"
    proc = _spawn(["run", str(seq), "--out", str(out), "--config", _config(tmp_path), "--realtime", "--rate", "4"])
    text = interrupt_after(r"frames ([4-9]|[1-3]\d)/40", proc)  # drops may skip a count
    assert "interrupted (SIGINT)" in text, text[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "interrupted" and 1 <= m["frames_tracked"] < 40  # 4 or more taken or dropped
    stamps, T = read_tum(out / "trajectory.txt")
    assert len(stamps) == m["frames_tracked"] and np.all(np.isfinite(T))
    assert set(np.round(stamps, 6)) <= set(np.round(_stamps(seq), 6))
