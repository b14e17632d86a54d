"""`swarmsplat` on a disk that fills up at a chosen moment: `python full_disk_run.py WHERE AFTER ARGS...` runs the
console script with ARGS (as `swarmsplat ARGS` does, exit code and all) after `DiskFills(WHERE, AFTER).install()`.

DiskFills makes the disk full right after the run has written AFTER checkpoints, at the next write of WHERE:
"checkpoint" (the next checkpoint's data does not fit) or "journal" (the next pose journal block is half written,
then the disk is full). From then on every os.write, os.fsync and os.replace fails with ENOSPC, as on a real full
disk; writes through Python's file objects still land in their temporary files, but none of them is renamed into
place. Each checkpoint that is written whole is copied to `last-checkpoint.pkl` beside the run's folder, so a test
can compare it with what the folder keeps.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
from pathlib import Path

CHECKPOINT_TMP = ".checkpoint.pkl."  # kernels.fileio.atomic_path's temporary name for progress/checkpoint.pkl


def _full() -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


class DiskFills:
    def __init__(self, where: str, after: int):
        assert where in ("checkpoint", "journal"), where
        self.where, self.after = where, int(after)
        self.checkpoints = 0  # written whole so far
        self.full = False
        self._write, self._fsync, self._replace = os.write, os.fsync, os.replace

    def install(self, monkeypatch=None) -> "DiskFills":
        for name, fn in (("write", self.write), ("fsync", self.fsync), ("replace", self.replace)):
            if monkeypatch is not None:
                monkeypatch.setattr(os, name, fn)
            else:
                setattr(os, name, fn)
        return self

    def _armed(self) -> bool:
        return not self.full and self.checkpoints >= self.after

    def write(self, fd: int, data) -> int:
        if self.full:
            raise _full()
        if self.where == "journal" and self._armed() and _path(fd).endswith(".tum") and len(data) > 1:
            self.full = True  # half the block lands; the rest does not fit
            return self._write(fd, bytes(data[: len(data) // 2]))
        return self._write(fd, data)

    def fsync(self, fd: int) -> None:
        if self.full:
            raise _full()
        if self.where == "checkpoint" and self._armed() and CHECKPOINT_TMP in _path(fd):
            self.full = True
            raise _full()
        self._fsync(fd)

    def replace(self, src, dst, **kw) -> None:
        if self.full:
            raise _full()
        self._replace(src, dst, **kw)
        dst = Path(dst)
        if dst.name == "checkpoint.pkl" and dst.parent.name == "progress":
            self.checkpoints += 1
            shutil.copyfile(dst, dst.parent.parent.parent / "last-checkpoint.pkl")


def _path(fd: int) -> str:
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return ""


if __name__ == "__main__":
    DiskFills(sys.argv[1], int(sys.argv[2])).install()
    from swarmsplat.slam.cli import main

    sys.argv = ["swarmsplat", *sys.argv[3:]]
    sys.exit(main())
