"""Make a team out of one recording: `split_sequence` cuts a sequence into overlapping frame ranges, one agent
each. Every agent then starts in its own frame (its first camera), so the split exercises inter-agent loop
closure and frame joining on real data where only single-camera recordings exist."""

from __future__ import annotations

from typing import Sequence

from kernels.errors import InputError

from .datasets import ImageSequence, MultiAgentDataset


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


def split_sequence(seq: ImageSequence, ranges: Sequence[tuple[int, int]],
                   names: Sequence[str] | None = None) -> MultiAgentDataset:
    """One agent per half-open frame range, e.g. [(0, 3), (2, 5)] (ranges may overlap)."""
    if not ranges:
        raise InputError("split_sequence needs at least one frame range")
    names = list(names) if names else [f"agent_{k}" for k in range(len(ranges))]
    if len(names) != len(ranges):
        raise InputError(f"{len(ranges)} ranges but {len(names)} names")
    agents = [sub_sequence(seq, a, b, n) for (a, b), n in zip(ranges, names)]
    return MultiAgentDataset(root=seq.root, agents=agents, name=f"{seq.name} split {list(ranges)}",
                             kind="rgbd" if seq.is_rgbd else "mono", meta={"split_of": str(seq.root)})
