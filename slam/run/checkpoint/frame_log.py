"""The frames a live agent has read since its last checkpoint, on disk (out/progress/frames/).

An agent on a recording resumes by reading again the frames after its checkpoint. On live topics those frames are
gone once read: without a log, a killed live agent loses every frame between its last checkpoint and the kill,
and a team member would also make other keyframes under the ids its killed process had already sent after that
checkpoint. So a live agent (slam.run.live, slam.run.team_link.live_agent) writes each frame here before it
tracks it, and forgets the frames a checkpoint has made unnecessary; `--resume` tracks the logged frames again
first (the same frames under the same indices: a team member's server drops what it already had by id,
slam.run.team_link.member) and then the frames that arrive now, numbered after them.

One file a frame, `<index>.npz`, uncompressed (colour uint8, depth float32 metres, the timestamp), written in one
rename: a kill leaves whole files only. At 640x480 a frame is ~2.1 MB and ~3 ms to write (a page-cache write, no
fsync); the folder holds the frames since the last checkpoint (config checkpoint.every_submaps; with 0 no
checkpoint is written and nothing is logged).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path, output_dir, remove_leftovers

FRAMES = Path("progress") / "frames"


class FrameLog:
    """out/progress/frames/: `append` each frame before tracking it, `trim(k)` once a checkpoint needs no frame
    before k, `replay(k)` the frames from k on (in index order), `clear` when the server has everything."""

    def __init__(self, out: str | os.PathLike):
        self.dir = output_dir(Path(out) / FRAMES, "--out frame log")
        # A kill during `append` leaves its temporary file (never a frame: it is not read). One process owns `out`
        # (its lock), so whatever such file is here now is a leftover.
        remove_leftovers(self.dir, "*", ".npz")

    def _files(self) -> list[tuple[int, Path]]:
        found = []
        for p in self.dir.glob("*.npz"):
            if p.stem.isdigit():
                found.append((int(p.stem), p))
        return sorted(found)

    def append(self, frame) -> None:
        """Write `frame` (a slam.io.datasets Frame, `index` its index in this agent's stream) as one file."""
        path = self.dir / f"{int(frame.index):09d}.npz"
        arrays = {"timestamp": np.float64(frame.timestamp), "color": np.ascontiguousarray(frame.color)}
        if frame.depth is not None:
            arrays["depth"] = np.ascontiguousarray(frame.depth, np.float32)
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)

    def trim(self, before: int) -> None:
        """Forget the frames with an index below `before` (a checkpoint resumes at `before`)."""
        for k, p in self._files():
            if k >= before:
                break
            p.unlink(missing_ok=True)

    def replay(self, start: int):
        """The logged frames with index >= `start`, in index order, as Frames."""
        from swarmsplat.slam.io.datasets.base import Frame

        for k, p in self._files():
            if k < start:
                continue
            try:
                with np.load(p) as z:
                    depth = z["depth"] if "depth" in z.files else None
                    frame = Frame(index=k, timestamp=float(z["timestamp"]), color=z["color"], depth=depth)
            except (OSError, ValueError, KeyError, EOFError) as e:
                raise InputError(f"--resume: {p}: a logged frame that does not read back ({type(e).__name__}: "
                                 f"{str(e).splitlines()[0] if str(e) else 'damaged'}); remove it to resume without "
                                 f"it") from None
            yield frame

    def clear(self) -> None:
        """Forget every logged frame (a new run in the folder, or a run whose work is all kept)."""
        for _, p in self._files():
            p.unlink(missing_ok=True)
