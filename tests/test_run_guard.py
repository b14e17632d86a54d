"""A long run never loses its work: a corrupt frame is skipped and listed (`--strict` stops instead),
an interrupt sent to a running `swarmsplat run` leaves a readable trajectory of every frame tracked before it
and a metrics.json with status "interrupted", a failure leaves status "failed", and a second signal while the
partial results are written exits at once."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig

REPO = Path(__file__).resolve().parents[1]
QUICK = {  # tiny images, a handful of iterations (as tests/test_agent.py)
    "image": {"max_width": 160},
    "tracking": {"iterations": 8, "refine_max_width": 80, "pyramid_levels": 1, "coarse_max_width": 160},
    "mapping": {"max_width": 80, "iterations": 8, "first_iterations": 20, "seed_stride": 2},
    "submaps": {"keep_keyframe_width": 80},
}


def _sequence(root: Path, frames: int, agents: int = 1) -> Path:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    return generate(root, GeneratorConfig.preset("tiny", agents=agents, frames=frames, seed=1))


def _corrupt(png: Path) -> None:
    png.write_bytes(png.read_bytes()[:60])  # a truncated file: the header survives, the image data does not


def _config(tmp_path: Path) -> str:
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(SlamConfig().override(QUICK).to_yaml())
    return str(cfg)


def _stamps(seq: Path) -> np.ndarray:
    from swarmsplat.slam.io.datasets import load_sequence

    return load_sequence(seq).timestamps


def test_corrupt_frame_is_skipped_and_strict_stops(tmp_path, capsys):
    from swarmsplat.slam.dense.ply import load_ply
    from swarmsplat.slam.io.trajectory import read_tum

    seq = _sequence(tmp_path / "data", 6) / "agent_0"
    _corrupt(seq / "depth" / "000003.png")
    cfg = _config(tmp_path)
    out = tmp_path / "run"
    with pytest.warns(RuntimeWarning, match="frame 3 skipped: unreadable: cannot decode image"):
        assert main(["run", str(seq), "--out", str(out), "--config", cfg, "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and m["frames"] == 6 and m["frames_tracked"] == 5
    assert [s["frame"] for s in m["skipped_frames"]] == [3]
    assert "depth/000003.png" in m["skipped_frames"][0]["reason"]
    stamps, _ = read_tum(out / "trajectory.txt")
    np.testing.assert_allclose(stamps, np.delete(_stamps(seq), 3), atol=1e-6)  # the whole run minus that frame
    assert m["ate_rmse"] is not None and m["psnr"] is not None

    strict = tmp_path / "strict"
    capsys.readouterr()
    assert main(["run", str(seq), "--out", str(strict), "--config", cfg, "--quiet", "--strict"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("swarmsplat run:")]
    assert len(err) == 1 and "cannot decode image" in err[0] and "000003.png" in err[0], err
    m = json.loads((strict / "metrics.json").read_text())  # what was done before the abort is kept
    assert m["status"] == "failed" and "cannot decode image" in m["reason"] and m["frames_tracked"] == 3
    assert len(read_tum(strict / "trajectory.txt")[0]) == 3
    assert len(load_ply(strict / "map.ply")) == m["gaussians"] > 0 and (strict / "loops.csv").is_file()


def test_failure_mid_run_writes_status_failed(tmp_path, monkeypatch):
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.run.sequence import run_sequence
    from swarmsplat.slam.io.trajectory import read_tum

    seq = _sequence(tmp_path / "data", 4) / "agent_0"
    real = Agent.step

    def step(self, index, *args):
        if index == 2:
            raise RuntimeError("boom")
        return real(self, index, *args)

    monkeypatch.setattr(Agent, "step", step)
    with pytest.raises(RuntimeError, match="boom"):
        run_sequence(seq, tmp_path / "out", SlamConfig().override(QUICK), progress=False)
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["status"] == "failed" and m["reason"] == "RuntimeError: boom" and m["frames_tracked"] == 2
    assert len(read_tum(tmp_path / "out" / "trajectory.txt")[0]) == 2 and "partial_errors" not in m
    assert {"trajectory.txt", "map.ply", "loops.csv", "metrics.json"} <= set(m["written"])


class _Progress:
    """Reads a child's stderr (its progress lines) and remembers what it said."""

    def __init__(self, proc: subprocess.Popen):
        self.text = ""
        self._t = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._t.start()

    def _read(self, proc):
        for chunk in iter(lambda: proc.stderr.read(1), ""):
            self.text += chunk

    def wait_for(self, needle: str, proc: subprocess.Popen, timeout: float = 240.0) -> None:
        t0 = time.time()
        while not re.search(needle, self.text):  # a regular expression
            assert proc.poll() is None, f"ended early:\n{self.text[-2000:]}"
            assert time.time() - t0 < timeout, f"never saw {needle!r}:\n{self.text[-2000:]}"
            time.sleep(0.05)

    def done(self) -> str:
        self._t.join(10)
        return self.text


def _spawn(args: list[str], **kw) -> subprocess.Popen:
    # A progress line after every update (stderr is a pipe: plain lines, by default one per 10 s).
    env = {**os.environ, "PYTHONPATH": str(REPO), "SWARMSPLAT_PROGRESS_INTERVAL": "0"}
    return subprocess.Popen([sys.executable, "-m", "swarmsplat.slam", *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, cwd=REPO, env=env, **kw)


def interrupt_after(needle: str, proc: subprocess.Popen) -> str:
    """Send SIGINT once the child's progress matches `needle` (a regular expression); it must exit 130 within 15 s. Returns its stderr."""
    log = _Progress(proc)
    log.wait_for(needle, proc)
    t0 = time.time()
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130
    took = time.time() - t0
    text = log.done()
    assert took < 15, f"{took:.1f} s from SIGINT to exit"
    return text


def test_sigint_mid_run_keeps_every_tracked_frame(tmp_path):
    """The issue's report: Ctrl-C after some frames of `swarmsplat run` (started, as from a script with `&`, with
    SIGINT ignored by its parent) must stop the run within seconds and keep what was tracked."""
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    seq = _sequence(tmp_path / "data", 20) / "agent_0"
    out = tmp_path / "run"
    proc = _spawn(["run", str(seq), "--out", str(out), "--config", _config(tmp_path)],
                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    text = interrupt_after("frames 3/20", proc)
    assert "swarmsplat run: interrupted (SIGINT)" in text, text[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["reason"] == "SIGINT"
    n = m["frames_tracked"]
    assert 3 <= n < 20 and m["frames"] == 20
    traj = evo_fi.read_tum_trajectory_file(str(out / "trajectory.txt"))
    assert traj.num_poses == n and np.all(np.isfinite(traj.positions_xyz))
    np.testing.assert_allclose(traj.timestamps, _stamps(seq)[:n], atol=1e-6)  # every frame before the signal
    assert (out / "map.ply").is_file() and (out / "loops.csv").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no half-written temporary files


def test_sigterm_mid_team_run(tmp_path):
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    data = _sequence(tmp_path / "data", 10, agents=2)
    out = tmp_path / "team"
    proc = _spawn(["run", str(data), "--out", str(out), "--config", _config(tmp_path)])
    log = _Progress(proc)
    log.wait_for("round 2/10", proc)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 130
    assert "interrupted (SIGTERM)" in log.done()
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["reason"] == "SIGTERM"
    for a in m["agents"]:
        assert a["frames_tracked"] >= 2
        traj = evo_fi.read_tum_trajectory_file(str(out / "trajectories" / f"{a['name']}.txt"))
        assert traj.num_poses == a["frames_tracked"]
    assert set(m["maps"]) <= {"map.ply", "map_agent_1.ply"} and all((out / f).is_file() for f in m["maps"])
    assert (out / "loops.csv").is_file() and (out / "config.yaml").is_file()


def test_second_signal_while_saving_exits_at_once():
    code = ("import time\n"
            "from swarmsplat.slam.run.guard import guarded_run\n"
            "with guarded_run(lambda status, reason: (print('saving', flush=True), time.sleep(60)), what='t'):\n"
            "    print('ready', flush=True)\n"
            "    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGINT)
    assert proc.stdout.readline().strip() == "saving"
    t0 = time.time()
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 130 and time.time() - t0 < 5
    assert "SIGINT again: exiting now" in proc.stderr.read()


def test_team_skips_a_corrupt_frame(tmp_path):
    from swarmsplat.slam.run.team import run_team

    data = _sequence(tmp_path / "data", 3, agents=2)
    _corrupt(data / "agent_1" / "rgb" / "000001.png")
    cfg = SlamConfig().override(QUICK)
    with pytest.warns(RuntimeWarning, match="agent_1: frame 1 skipped: unreadable"):
        m = run_team(data, tmp_path / "team", cfg, progress=False, render_views=1)
    assert m["status"] == "complete"
    a0, a1 = m["agents"]
    assert a0["skipped_frames"] == [] and a0["frames_tracked"] == 3
    assert [s["frame"] for s in a1["skipped_frames"]] == [1] and a1["frames_tracked"] == 2
    assert "rgb/000001.png" in a1["skipped_frames"][0]["reason"]


def test_swarm_and_pairs_skip_a_corrupt_keyframe_and_an_interrupted_swarm_keeps_its_outputs(tmp_path, monkeypatch):
    from swarmsplat.slam.run.pairs import metrics_path
    from swarmsplat.slam.flocc.swarm.node import RobotNode
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "mono", GeneratorConfig.preset("tiny", agents=2, frames=6, seed=1, mono=True))
    _corrupt(data / "agent_1" / "rgb" / "000002.png")  # a keyframe with --stride 2
    sched = tmp_path / "s.yaml"
    sched.write_text("ticks: 12\nframes_per_tick: 1\nwindows:\n  - {start: 2, end: 12, robots: [0, 1]}\n")
    out = tmp_path / "swarm"
    with pytest.warns(RuntimeWarning, match="agent_1: frame 2 skipped: unreadable") as got:
        assert main(["swarm", str(data), "--out", str(out), "--stride", "2", "--schedule", str(sched)]) == 0
    assert sum("frame 2 skipped" in str(w.message) for w in got) == 1  # one warning line per frame
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and [(s["agent"], s["frame"]) for s in m["skipped_frames"]] == [("agent_1", 2)]
    assert np.loadtxt(out / "agent_1.txt").shape == (2, 8) and m["images_bytes"]["agent_1"]["keyframes"] == 2
    assert set(m["ate"]["per_robot_rmse"]) == {"agent_0", "agent_1"}

    csv = tmp_path / "pairs" / "pairs.csv"
    with pytest.warns(RuntimeWarning, match="agent_1: frame 2 skipped"):
        assert main(["pairs", str(data), "--out", str(csv), "--stride", "2", "--quiet"]) == 0
    pm = json.loads(metrics_path(csv).read_text())
    assert pm["status"] == "complete" and pm["n_keyframes"] == 5 and [s["frame"] for s in pm["skipped_frames"]] == [2]

    real = RobotNode.step

    def step(self, tick):  # Ctrl-C during tick 6
        if tick == 6:
            raise KeyboardInterrupt
        return real(self, tick)

    monkeypatch.setattr(RobotNode, "step", step)
    cut = tmp_path / "cut"
    with pytest.warns(RuntimeWarning, match="frame 2 skipped"):
        assert main(["swarm", str(data), "--out", str(cut), "--stride", "2", "--schedule", str(sched)]) == 130
    m = json.loads((cut / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["reason"] == "KeyboardInterrupt"
    assert (cut / "agent_0.txt").is_file() and (cut / "odometry" / "agent_0.txt").is_file()
