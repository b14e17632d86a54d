import os
import stat

import pytest

from swarmsplat.kernels.fileio import atomic_path, atomic_write_text


def test_atomic_write_replaces_and_keeps_normal_permissions(tmp_path):
    p = tmp_path / "out.json"
    atomic_write_text(p, "one")
    atomic_write_text(p, "two")
    assert p.read_text() == "two"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask
    assert [f.name for f in tmp_path.iterdir()] == ["out.json"]


def test_failed_write_leaves_previous_file_and_no_temp(tmp_path):
    p = tmp_path / "out.txt"
    atomic_write_text(p, "good")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert p.read_text() == "good"
    assert [f.name for f in tmp_path.iterdir()] == ["out.txt"]
