"""Finished submaps' Gaussians as files in the run folder: `submaps/NNNN.bin`, one per submap, each written once,
atomically (a reader never sees half a file) and fsync'd before the run goes on, read back on demand.

The bytes are whatever the caller stores (slam.dense.submap_codec's form); this module only keeps them. It
pickles as its folder, so a checkpointed agent refers to its submaps' files instead of holding them.
"""

from __future__ import annotations

import os
from pathlib import Path

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path


class SubmapFiles:
    """A folder of `NNNN.bin` files keyed by submap id."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder).resolve()

    def path(self, key: int) -> Path:
        return self.folder / f"{int(key):04d}.bin"

    def describe(self, key: int) -> str:
        return str(self.path(key))

    def write(self, key: int, data: bytes) -> None:
        """Write submap `key`'s bytes and make them durable (file and folder fsync'd); InputError naming the file
        when the disk refuses (full, read-only)."""
        path = self.path(key)
        try:
            with atomic_path(path) as tmp:
                with open(tmp, "wb") as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
            fd = os.open(self.folder, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as e:
            raise InputError(f"cannot write {path}: {e.strerror or e}") from None

    def read(self, key: int) -> bytes:
        path = self.path(key)
        try:
            return path.read_bytes()
        except OSError as e:
            raise InputError(f"cannot read {path}: {e.strerror or e} (a finished submap of this run, expected "
                             f"in its output folder)") from None

    def nbytes(self) -> int:
        return sum(p.stat().st_size for p in self.folder.glob("*.bin"))

    def __repr__(self) -> str:
        return f"SubmapFiles({str(self.folder)!r})"
