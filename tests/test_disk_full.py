"""A full disk or a read-only output folder: `swarmsplat run` says so in one line naming the folder or the file it
could not write (exit 2 before any work, 1 mid-run), the run's folder keeps its last checkpoint and a journal of
whole lines, and `--resume` once there is space again ends with the uninterrupted run's result."""

from __future__ import annotations

import errno
import json
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from full_disk_run import DiskFills
from swarmsplat.kernels.errors import OutputError
from swarmsplat.kernels.fileio import atomic_write_text
from swarmsplat.slam.cli import main
from test_run_checkpoint import FRAMES, REPO, SINGLE_OUTPUTS, TEAM_OUTPUTS, _assert_same_files, _config, _run

FULL = "the disk is full (No space left on device)"


def _hint(out: Path) -> str:
    return f"; {out} keeps the run's last checkpoint: free some space, then run the same command with --resume"


def _error_lines(err: str) -> list[str]:
    """stderr without the kernel libraries' own start-up lines."""
    return [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("Warp ", "[I "))]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("data")
    return generate(root, GeneratorConfig.preset("tiny", agents=1, frames=FRAMES, seed=1)) / "agent_0"


@pytest.fixture(scope="module")
def whole(sequence, tmp_path_factory) -> tuple[Path, str]:
    """The uninterrupted run (in its own process, as the others) and its config file."""
    where = tmp_path_factory.mktemp("whole")
    cfg = _config(where)
    _run(["run", str(sequence), "--out", str(where / "out"), "--config", cfg, "--quiet"])
    return where / "out", cfg


@pytest.mark.parametrize("where, name", [("checkpoint", "checkpoint.pkl"), ("journal", "poses.tum")])
def test_a_full_disk_stops_the_run_in_one_line_and_resume_finishes_it(sequence, whole, tmp_path, where, name):
    reference, cfg = whole
    out = tmp_path / "out"
    args = ["run", str(sequence), "--out", str(out), "--config", cfg, "--quiet"]
    # the disk fills up after the second checkpoint: at the third one, or half-way through a journal block
    _run_on_a_disk_that_fills(where, args, out / "progress" / name)

    # the last checkpoint written whole is there, byte for byte; no temporary file is left anywhere
    ckpt = out / "progress" / "checkpoint.pkl"
    assert ckpt.read_bytes() == (tmp_path / "last-checkpoint.pkl").read_bytes()
    with open(ckpt, "rb") as f:
        header = pickle.load(f)
    assert 0 < header["next_frame"] < FRAMES
    assert not [p for p in out.rglob(".*")], "a temporary file was left behind"
    # the journal holds whole lines up to a keyframe: a prefix of the uninterrupted run's, at least up to the
    # checkpoint (the block the disk cut in half is gone)
    journal = (out / "progress" / "poses.tum").read_bytes()
    assert journal.endswith(b"\n") and (reference / "progress" / "poses.tum").read_bytes().startswith(journal)
    assert len(journal) >= header["journal"][0]
    assert not (out / "trajectory.txt").exists()  # nothing was renamed into place on the full disk

    _run([*args, "--resume"])  # space is back
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and m["frames_tracked"] == FRAMES
    _assert_same_files(out, reference, SINGLE_OUTPUTS)
    assert not ckpt.exists()


def test_a_team_stopped_by_a_full_disk_resumes_to_the_uninterrupted_result(sequence, tmp_path):
    """The in-process team: the disk fills up while its third checkpoint is written (cloud route off, as in
    tests/test_run_checkpoint.py, so two processes give the same result bit for bit)."""
    cfg = _config(tmp_path, server={"cloud_route": False})
    split = ["--split", "0:22,22:45"]
    reference = tmp_path / "whole"
    _run(["run", str(sequence), "--out", str(reference), "--config", cfg, "--quiet", *split])
    out = tmp_path / "out"
    args = ["run", str(sequence), "--out", str(out), "--config", cfg, "--quiet", *split]
    _run_on_a_disk_that_fills("checkpoint", args, out / "progress" / "checkpoint.pkl")
    ckpt = out / "progress" / "checkpoint.pkl"
    assert ckpt.read_bytes() == (tmp_path / "last-checkpoint.pkl").read_bytes()
    assert not [p for p in out.rglob(".*")], "a temporary file was left behind"

    _run([*args, "--resume"])
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and not ckpt.exists()
    _assert_same_files(out, reference, TEAM_OUTPUTS)


def _run_on_a_disk_that_fills(where: str, args: list[str], refused: Path) -> None:
    """`swarmsplat ARGS` in its own process on a disk that fills up after the run's second checkpoint
    (full_disk_run.DiskFills(where, 2)): it must end with exit 1 and one line naming `refused`."""
    out = Path(args[args.index("--out") + 1])
    proc = subprocess.run([sys.executable, str(REPO / "tests" / "full_disk_run.py"), where, "2", *args],
                          capture_output=True, text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert _error_lines(proc.stderr) == [f"swarmsplat run: error: cannot write {refused}: {FULL}{_hint(out)}"]


def test_a_failed_checkpoint_keeps_the_previous_one(tmp_path, monkeypatch):
    from swarmsplat.slam.run.checkpoint import save_checkpoint

    agent = SimpleNamespace(keyframes=[], gmap=SimpleNamespace(submaps=[]), note="first")
    path = save_checkpoint(tmp_path, {}, agent, next_frame=3, journal=(10, 1), wall_s=1.0)
    before = path.read_bytes()
    DiskFills("checkpoint", 0).install(monkeypatch)  # the next checkpoint's data does not fit
    agent.note = "second"
    with pytest.raises(OutputError, match=f"cannot write {path}: the disk is full") as e:
        save_checkpoint(tmp_path, {}, agent, next_frame=6, journal=(20, 2), wall_s=2.0)
    assert e.value.full and e.value.exit_code == 1
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["checkpoint.pkl"]
    # an output written through a file object: the previous version stays too
    target = tmp_path / "trajectory.txt"
    target.write_text("old\n")

    def half_then_full(self, text):
        Path.write_bytes(self, text[: len(text) // 2].encode())
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_text", half_then_full)
    with pytest.raises(OutputError, match=re.escape(f"cannot write {target}: {FULL}")):
        atomic_write_text(target, "new content\n")
    assert target.read_bytes() == b"old\n" and sorted(p.name for p in tmp_path.iterdir()) == [
        "progress", "trajectory.txt"]


def test_a_journal_block_the_disk_cuts_in_half_is_taken_back(tmp_path, monkeypatch):
    from swarmsplat.slam.run.checkpoint import PoseJournal
    from swarmsplat.slam.run.checkpoint.journal import HEADER

    path = tmp_path / "progress" / "poses.tum"
    with PoseJournal(path) as journal:
        journal._append("0.000000 0 0 0 0 0 0 1\n")
        state = journal.state()
        DiskFills("journal", 0).install(monkeypatch)
        with pytest.raises(OutputError, match=f"cannot write {path}: the disk is full"):
            journal._append("0.100000 1 0 0 0 0 0 1\n0.200000 2 0 0 0 0 0 1\n")
        assert journal.state() == state
    assert path.read_text() == HEADER + "0.000000 0 0 0 0 0 0 1\n"


@pytest.fixture
def read_only(tmp_path, monkeypatch) -> Path:
    """A run's folder that cannot be written: mode 0500, or, for root (whom modes do not stop), one that os.access
    says so of."""
    ro = tmp_path / "ro"
    (ro / "progress").mkdir(parents=True)
    (ro / "config.yaml").write_text("{}\n")
    ro.chmod(0o500)
    if os.geteuid() == 0:
        access = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: Path(p) != ro and access(p, mode, **kw))
    yield ro
    ro.chmod(0o700)


@pytest.mark.parametrize("resume", [False, True])
def test_a_read_only_out_folder_is_one_line_before_any_work(sequence, read_only, monkeypatch, capsys, resume):
    import swarmsplat.slam.io.datasets as datasets

    def no_loading(*a, **kw):
        raise AssertionError("the dataset was loaded before the output folder was checked")

    monkeypatch.setattr(datasets, "load_dataset", no_loading)
    code = main(["run", str(sequence), "--out", str(read_only), "--quiet", *(["--resume"] if resume else [])])
    assert code == 2
    assert _error_lines(capsys.readouterr().err) == [
        f"swarmsplat run: error: --out {read_only}: cannot write in {read_only} (permission denied)"]
    assert sorted(p.name for p in read_only.iterdir()) == ["config.yaml", "progress"]

    # on a read-only file system the line says so
    monkeypatch.setattr(os, "statvfs", lambda p: SimpleNamespace(f_flag=os.ST_RDONLY))
    assert main(["run", str(sequence), "--out", str(read_only), "--quiet"]) == 2
    assert _error_lines(capsys.readouterr().err) == [
        f"swarmsplat run: error: --out {read_only}: cannot write in {read_only} (read-only file system)"]


def test_a_folder_that_refuses_the_first_write_is_one_line(sequence, tmp_path, monkeypatch, capsys):
    """A folder os.access calls writable that still refuses files (an ACL, a root-squashed NFS export): the run's
    first write, a probe before the first frame, fails with the same kind of line."""
    import tempfile

    out = tmp_path / "out"
    out.mkdir()
    mkstemp = tempfile.mkstemp

    def refuse(*a, dir=None, **kw):
        if dir is not None and Path(dir) == out:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(out / ".write-test"))
        return mkstemp(*a, dir=dir, **kw)

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main(["run", str(sequence), "--out", str(out), "--quiet", "--frames", "3"]) == 2
    assert _error_lines(capsys.readouterr().err) == [
        f"swarmsplat run: error: --out {out}: cannot write there (Permission denied)"]
    assert not list(out.iterdir())
