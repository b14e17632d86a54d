"""What every dataset loader returns: a `Sequence` of `Frame`s with a camera, and a `MultiAgentDataset`.

Frames: colour is RGB uint8 [H, W, 3]; depth is float32 metres [H, W] with 0 where invalid (None for a
monocular sequence); poses are `T_world_cam` 4x4 float64 (camera-to-world, OpenCV camera axes).
A sequence's pose arrays hold a row of NaN for a frame whose pose is unknown (e.g. EuRoC images recorded before
motion capture starts); that frame's `Frame.T_world_cam_gt` / `T_world_cam_odom` is then None.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Protocol, Sequence as Seq

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera


@dataclass
class Frame:
    index: int
    timestamp: float
    color: np.ndarray  # [H, W, 3] uint8 RGB
    depth: np.ndarray | None  # [H, W] float32 metres, 0 = invalid; None for monocular
    T_world_cam_gt: np.ndarray | None = None  # [4, 4] ground truth, if known
    T_world_cam_odom: np.ndarray | None = None  # [4, 4] metric odometry (monocular sequences), if given


class Sequence(Protocol):
    """One agent's recording. Frames load lazily on indexing, so long sequences stay out of memory."""

    name: str
    camera: PinholeCamera
    root: Path

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...

    @property
    def timestamps(self) -> np.ndarray: ...  # [N] seconds

    @property
    def gt_poses(self) -> np.ndarray | None: ...  # [N, 4, 4] T_world_cam (NaN rows where unknown), or None

    @property
    def odometry(self) -> np.ndarray | None: ...  # [N, 4, 4] T_world_cam from metric odometry, or None


@dataclass
class MultiAgentDataset:
    """A root folder holding one sequence per agent (named in `dataset.yaml`)."""

    root: Path
    agents: Seq[Sequence]
    name: str = ""
    kind: str = "rgbd"  # "rgbd" | "mono"
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.agents)
