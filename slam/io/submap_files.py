"""What a run moves out of memory, as files in its folder, each written once, atomically (a reader never sees half
a file) and fsync'd before the run goes on, read back on demand:

- finished submaps' Gaussians: `submaps/NNNN.bin`, one per submap (slam.dense.submap_codec's form);
- finished submaps' keyframe images: `keyframes/small/NNNN.bin` (the loop-closure copy) and
  `keyframes/mapping/NNNN.bin` (the mapping-resolution copy the final refinement fits), one per keyframe id
  (slam.dense.packed's stored form).

The bytes are whatever the caller stores; this module only keeps them. A store pickles as its folder, so a
checkpointed agent refers to the files instead of holding them.
"""

from __future__ import annotations

import os
from pathlib import Path

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path, refused_write


class SubmapFiles:
    """A folder of `NNNN.bin` files keyed by an integer id (a submap's, or a keyframe's)."""

    def __init__(self, folder: str | os.PathLike, what: str = "a finished submap"):
        self.folder = Path(folder).resolve()
        self.what = what  # named when a file is missing

    def path(self, key: int) -> Path:
        return self.folder / f"{int(key):04d}.bin"

    def describe(self, key: int) -> str:
        return str(self.path(key))

    def write(self, key: int, data: bytes) -> None:
        """Write submap `key`'s bytes and make them durable (file and folder fsync'd); OutputError naming the file
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
            raise refused_write(path, e) from None

    def read(self, key: int) -> bytes:
        path = self.path(key)
        try:
            return path.read_bytes()
        except OSError as e:
            raise InputError(f"cannot read {path}: {e.strerror or e} ({getattr(self, 'what', 'a finished submap')} "
                             f"of this run, expected in its output folder)") from None

    def nbytes(self) -> int:
        return sum(p.stat().st_size for p in self.folder.glob("*.bin"))

    def __repr__(self) -> str:
        return f"SubmapFiles({str(self.folder)!r})"


class KeyframeFiles:
    """Finished submaps' keyframe images in `folder`: `small` (SubmapFiles of the loop-closure copies) and `mapping`
    (of the mapping-resolution copies), keyed by keyframe id."""

    def __init__(self, folder: str | os.PathLike):
        self.small = SubmapFiles(Path(folder) / "small", "a keyframe's loop-closure image")
        self.mapping = SubmapFiles(Path(folder) / "mapping", "a keyframe's mapping-resolution image")

    @property
    def folder(self) -> Path:
        return self.small.folder.parent

    @folder.setter
    def folder(self, folder: str | os.PathLike) -> None:
        """Point both stores at `folder` (a resumed run whose folder has moved)."""
        self.small.folder = (Path(folder) / "small").resolve()
        self.mapping.folder = (Path(folder) / "mapping").resolve()

    def nbytes(self) -> int:
        return self.small.nbytes() + self.mapping.nbytes()

    def __repr__(self) -> str:
        return f"KeyframeFiles({str(self.folder)!r})"
