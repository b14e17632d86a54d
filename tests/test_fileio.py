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


def test_text_lines_refuses_binary_input_in_one_line(tmp_path):
    """An image given where a text file belongs (a g2o graph, a TUM trajectory) is an InputError naming file and
    line, never a UnicodeDecodeError."""
    from swarmsplat.graph.g2o import read_g2o
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import text_lines
    from swarmsplat.slam.io.trajectory import read_tum

    t = tmp_path / "t.txt"
    t.write_bytes(b"ok line\n\x89PNG\n")
    assert next(text_lines(t, "test")) == (1, "ok line\n")
    with pytest.raises(InputError, match=r"t\.txt:2: not a text test file"):
        list(text_lines(t, "test"))
    p = tmp_path / "x.png"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
    for read, what in ((lambda: list(text_lines(p, "test")), "test"), (lambda: read_g2o(p), "g2o"),
                       (lambda: read_tum(p), "trajectory")):
        with pytest.raises(InputError, match=rf"x\.png:1: not a text {what} file"):
            read()
