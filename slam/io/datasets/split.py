"""Make a team out of one recording: `split_sequence` cuts a sequence into frame ranges, one agent each (ranges
may overlap or be disjoint). Every agent then starts in its own frame (its first camera), so the split exercises
inter-agent loop closure and frame joining on real data where only single-camera recordings exist.

    ranges = parse_ranges("0:3,3:5")          # what `swarmsplat run SEQ --split 0:3,3:5` takes
    team_ds = split_sequence(seq, ranges)      # agent_0: frames 0-2, agent_1: frames 3-4
"""

from __future__ import annotations

import re
from typing import Sequence

from swarmsplat.kernels.errors import InputError

from swarmsplat.slam.io.datasets import ImageSequence, MultiAgentDataset

_RANGE = re.compile(r"^\s*(\d*)\s*:\s*(\d*)\s*$")


def parse_ranges(text: str, *, what: str = "--split") -> list[tuple[int | None, int | None]]:
    """'0:3,3:5' -> [(0, 3), (3, 5)]: comma-separated half-open frame ranges START:STOP (frame indices from 0).
    An empty START means 0 and an empty STOP the end of the sequence ('0:3,3:'). Raises InputError naming
    `what` and the bad item; whether a range fits the sequence is checked by split_sequence."""
    items = [s for s in str(text).split(",")]
    if not str(text).strip() or any(not s.strip() for s in items):
        raise InputError(f"{what}: expected comma-separated frame ranges START:STOP such as 0:3,3:5, got {text!r}")
    out: list[tuple[int | None, int | None]] = []
    for item in items:
        m = _RANGE.match(item)
        if not m:
            raise InputError(f"{what}: {item.strip()!r} is not a frame range START:STOP of non-negative integers "
                             f"(e.g. 0:3)")
        start, stop = (int(g) if g else None for g in m.groups())
        if start is not None and stop is not None and stop <= start:
            raise InputError(f"{what}: range {item.strip()!r} is empty (STOP must be greater than START)")
        out.append((start, stop))
    if len(out) < 2:
        raise InputError(f"{what}: a split needs at least two ranges (one per agent), got {text!r}")
    return out


def sub_sequence(seq: ImageSequence, start: int, stop: int, name: str | None = None) -> ImageSequence:
    """Frames [start, stop) of `seq` as a sequence of their own (frame indices restart at 0)."""
    n = len(seq)
    if not 0 <= start < stop <= n:
        raise InputError(f"frame range [{start}, {stop}) is not inside sequence '{seq.name}' of {n} frames")
    cut = lambda x: None if x is None else x[start:stop]  # noqa: E731
    return ImageSequence(name=name or f"{seq.name}_{start}_{stop}", root=seq.root, camera=seq.camera,
                         timestamps=seq.timestamps[start:stop], color_paths=seq.color_paths[start:stop],
                         depth_paths=cut(seq.depth_paths), depth_scale=seq.depth_scale, gt_poses=cut(seq.gt_poses),
                         odometry=cut(seq.odometry), color_transform=getattr(seq, "_color_transform", None))


def split_sequence(seq: ImageSequence, ranges: Sequence[tuple[int | None, int | None]],
                   names: Sequence[str] | None = None) -> MultiAgentDataset:
    """One agent per half-open frame range, e.g. [(0, 3), (3, 5)] (ranges may overlap; None: 0 / the end)."""
    if not ranges:
        raise InputError("split_sequence needs at least one frame range")
    names = list(names) if names else [f"agent_{k}" for k in range(len(ranges))]
    if len(names) != len(ranges):
        raise InputError(f"{len(ranges)} ranges but {len(names)} names")
    ranges = [(0 if a is None else int(a), len(seq) if b is None else int(b)) for a, b in ranges]
    agents = [sub_sequence(seq, a, b, n) for (a, b), n in zip(ranges, names)]
    return MultiAgentDataset(root=seq.root, agents=agents, name=f"{seq.name} split {list(ranges)}",
                             kind="rgbd" if seq.is_rgbd else "mono", meta={"split_of": str(seq.root)})
