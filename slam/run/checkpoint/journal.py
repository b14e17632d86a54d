"""The pose journal: an append-only TUM file that a hard kill (`kill -9`, OOM, power) cannot take away.

At each keyframe the frames tracked since the previous one are appended, keyframe included, each at its world pose
as known at that moment (later loop closures move them in trajectory.txt, not here), in one write() followed by
fsync(): the file holds every tracked frame up to the last keyframe, whole lines only, and is readable at any moment
(`swarmsplat eval --est out/progress/poses.tum`, evo, `slam.io.trajectory.read_tum`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.fileio import refused_write

from swarmsplat.slam.dense.submaps import frame_local_poses

HEADER = ("# swarmsplat pose journal: every frame tracked up to the last keyframe, at its world pose as known when "
          "that keyframe was made\n# timestamp tx ty tz qx qy qz qw\n")


class PoseJournal:
    """Appends one agent's tracked frames to `path` at each of its keyframes (`follow` after every Agent.step).

    resume: (bytes, frames) of a checkpoint (`state()` when it was taken): the file is cut back to that size and the
    journal goes on from the frame after; None starts a new file.
    """

    def __init__(self, path: str | Path, *, resume: tuple[int, int] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        new = resume is None or resume[1] == 0 or not self.path.is_file()
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if new else 0), 0o644)
        except OSError as e:
            raise refused_write(self.path, e) from None
        if new:
            self.frames, self._size = 0, 0
            self._append(HEADER)
            _fsync_dir(self.path.parent)  # the file's name survives a power cut too
        else:
            self._size, self.frames = resume
            os.ftruncate(self._fd, self._size)  # frames journaled after the checkpoint are tracked again
            os.fsync(self._fd)

    def state(self) -> tuple[int, int]:
        """(bytes written, frames journaled): what a checkpoint stores to resume the journal."""
        return self._size, self.frames

    def follow(self, agent) -> int:
        """After `agent.step`: if it made a keyframe, append every frame tracked since the last append (the
        keyframe is the newest). Returns how many frames were appended."""
        recs = agent.poses[self.frames:]
        if not recs or not agent.keyframes or recs[-1].frame_index != agent.keyframes[-1].frame_index:
            return 0  # nothing new, or the newest frame is no keyframe
        subs = agent.gmap.submaps
        T = np.stack([subs[r.submap_id].T_world_local @ L for r, L in zip(recs, frame_local_poses(recs, agent.keyframes))])
        xyz, q = se3.to_tum(T)
        self._append("".join(f"{r.timestamp:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {qq[0]:.9f} {qq[1]:.9f} "
                             f"{qq[2]:.9f} {qq[3]:.9f}\n" for r, p, qq in zip(recs, xyz, q)))
        self.frames += len(recs)
        return len(recs)

    def _append(self, text: str) -> None:
        """Append `text` (whole lines) and fsync; when the disk refuses (full, ...), cut the file back to its last
        whole block, so it still ends at a keyframe, and raise OutputError naming it."""
        data = text.encode()
        size = len(data)
        try:
            while data:  # one write for a block of lines; a short write goes on where it stopped
                data = data[os.write(self._fd, data):]
            os.fsync(self._fd)
        except OSError as e:
            try:
                os.ftruncate(self._fd, self._size)  # shrinking needs no space
            except OSError:
                pass
            raise refused_write(self.path, e) from None
        self._size += size

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> "PoseJournal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
