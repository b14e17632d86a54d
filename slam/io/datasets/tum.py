"""TUM RGB-D benchmark sequences as downloaded (`rgbd_dataset_freiburg1_xyz/`): rgb.txt, depth.txt,
groundtruth.txt, rgb/, depth/ (uint16, 5000 units per metre).

RGB and depth come from two clocks, so they are paired one-to-one by time (within 20 ms, TUM's `associate.py`
rule) and frames without a partner are dropped. Ground truth (100 Hz motion capture) is taken at each RGB
stamp from the nearest sample within 20 ms. Intrinsics are TUM's published values for the freiburg1/2/3
sensors, recognised from the folder name, or the ROS default when the name does not tell.
"""

from __future__ import annotations

import re
from pathlib import Path

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import read_tum

from ._sequence import ImageSequence, poses_at
from .associate import associate_unique
from .folder import read_image_list

TUM_DEPTH_SCALE = 5000.0
PAIR_MAX_DIFF = 0.02
GT_MAX_DIFF = 0.02

# Published pinhole parameters (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats), 640x480.
TUM_CAMERAS = {
    "freiburg1": PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": PinholeCamera(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": PinholeCamera(535.4, 539.2, 320.1, 247.6, 640, 480),
    "default": PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480),
}


def tum_camera_for(path: Path) -> PinholeCamera:
    m = re.search(r"(?:freiburg|fr)([123])", str(Path(path).resolve()).lower())
    return TUM_CAMERAS[f"freiburg{m.group(1)}"] if m else TUM_CAMERAS["default"]


def is_tum_sequence(path: Path) -> bool:
    return (path / "rgb.txt").is_file() and (path / "depth.txt").is_file() and not (path / "calibration.yaml").is_file()


def load_tum_sequence(path: str | Path, *, camera: PinholeCamera | None = None, name: str | None = None,
                      max_diff: float = PAIR_MAX_DIFF) -> ImageSequence:
    """Load a TUM RGB-D sequence folder; `camera` overrides the intrinsics guessed from the folder name."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    t_rgb, rgb = read_image_list(root / "rgb.txt")
    t_d, depth = read_image_list(root / "depth.txt")
    i_rgb, i_d = associate_unique(t_rgb, t_d, max_diff)
    if len(i_rgb) == 0:
        raise InputError(f"{root}: no RGB frame has a depth frame within {max_diff} s")
    gt = None
    if (root / "groundtruth.txt").is_file():
        t_gt, T_gt = read_tum(root / "groundtruth.txt")
        gt = poses_at(t_rgb[i_rgb], t_gt, T_gt, GT_MAX_DIFF)
    return ImageSequence(
        name=name or root.name, root=root, camera=camera or tum_camera_for(root), timestamps=t_rgb[i_rgb],
        color_paths=[rgb[k] for k in i_rgb], depth_paths=[depth[k] for k in i_d], depth_scale=TUM_DEPTH_SCALE,
        gt_poses=gt,
    )
