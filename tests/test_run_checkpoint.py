"""A run survives a hard kill: `swarmsplat run` appends every frame up to its last keyframe to progress/poses.tum
(fsync'd at each keyframe), so SIGKILL loses at most the frames since."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig

REPO = Path(__file__).resolve().parents[1]
# Tiny images and few iterations (as tests/test_run_guard.py); a keyframe every 3 frames and a submap every 2
# keyframes; no map refinement (seconds saved, nothing to test there).
QUICK = {
    "image": {"max_width": 160},
    "tracking": {"iterations": 8, "refine_max_width": 80, "pyramid_levels": 1, "coarse_max_width": 160},
    "mapping": {"max_width": 80, "iterations": 8, "first_iterations": 20, "seed_stride": 2},
    "submaps": {"keep_keyframe_width": 80, "max_keyframes": 2},
    "keyframes": {"every": 3},
    "map_refine": {"iterations_per_keyframe": 0},
}
FRAMES = 45


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("data")
    return generate(root, GeneratorConfig.preset("tiny", agents=1, frames=FRAMES, seed=1)) / "agent_0"


def _config(where: Path, **changes) -> str:
    cfg = where / "quick.yaml"
    cfg.write_text(SlamConfig().override(QUICK).override(changes).to_yaml())
    return str(cfg)


def _spawn(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "swarmsplat.slam", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, cwd=REPO, env=env)


def _journal_frames(path: Path) -> int:
    return sum(1 for ln in path.read_text().splitlines() if ln and not ln.startswith("#")) if path.is_file() else 0


def test_kill_9_keeps_every_frame_up_to_the_last_keyframe(sequence, tmp_path):
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.io.trajectory import read_tum

    cfg = _config(tmp_path)
    whole = tmp_path / "whole"
    assert main(["run", str(sequence), "--out", str(whole), "--config", cfg, "--quiet"]) == 0
    m_whole = json.loads((whole / "metrics.json").read_text())
    kf_stamps = read_tum(whole / "keyframes.txt")[0]

    out = tmp_path / "killed"
    journal = out / "progress" / "poses.tum"
    proc = _spawn(["run", str(sequence), "--out", str(out), "--config", cfg, "--quiet"])
    t0 = time.time()
    # mid-run: the journal holds a third of the frames, but not all of them
    while _journal_frames(journal) < FRAMES // 3:
        assert proc.poll() is None, "the run ended before it could be killed"
        assert time.time() - t0 < 50, "not a third of the frames within 50 s"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(timeout=10) == -signal.SIGKILL
    assert not (out / "metrics.json").exists()  # no partial results: the process had no chance to write them

    stamps, T = read_tum(journal)  # whole lines only, every frame up to the last keyframe, in order, once
    seq_stamps = load_sequence(sequence).timestamps
    assert FRAMES // 3 <= len(stamps) < FRAMES
    np.testing.assert_allclose(stamps, seq_stamps[:len(stamps)], atol=1e-6)
    assert np.isclose(kf_stamps, stamps[-1], atol=1e-6).any(), "the journal ends at a keyframe"
    # the same frames at the same poses as the uninterrupted run's journal (one machine, one backend: the run
    # is deterministic), cut at a line's end
    whole_journal = (whole / "progress" / "poses.tum").read_bytes()
    assert whole_journal.startswith(journal.read_bytes()) and journal.read_bytes().endswith(b"\n")
    assert np.all(np.isfinite(T)) and m_whole["frames_tracked"] == FRAMES
    assert main(["eval", "--gt", str(sequence / "groundtruth.txt"), "--est", str(journal)]) == 0  # as it is


def test_a_team_run_journals_every_agent(sequence, tmp_path):
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.io.trajectory import read_tum

    out = tmp_path / "team"
    assert main(["run", str(sequence), "--out", str(out), "--config", _config(tmp_path), "--quiet",
                 "--split", "0:12,12:24"]) == 0
    seq_stamps = load_sequence(sequence).timestamps
    for name, first in (("agent_0", 0), ("agent_1", 12)):
        stamps, T = read_tum(out / "progress" / f"{name}.tum")
        # every frame up to the agent's last keyframe (one at least every keyframes.every = 3 frames)
        assert 12 - 2 <= len(stamps) <= 12 and np.all(np.isfinite(T))
        np.testing.assert_allclose(stamps, seq_stamps[first:first + len(stamps)], atol=1e-6)
