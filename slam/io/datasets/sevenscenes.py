"""Microsoft RGB-D Dataset 7-Scenes (Shotton et al. 2013) as downloaded, one `seq-NN/` folder per recording:

    <scene>/seq-01/frame-000000.color.png   640x480 colour (.jpg accepted)
                   frame-000000.depth.png   uint16 millimetres, 65535 = invalid (returned as 0)
                   frame-000000.pose.txt    T_world_cam, 4x4 camera-to-world (KinectFusion's depth-camera pose)
    <scene>/seq-02/ ...                      the sequences of one scene share one world frame

`load_dataset(<scene>)` makes a team with one agent per `seq-NN/` folder; `load_dataset(<scene>/seq-01)` one agent.

Cameras. 7-Scenes publishes only the depth camera's intrinsics (focal length 585 px, principal point (320, 240))
and its colour and depth are not registered. `camera` is that depth camera, and by default each colour image is
resampled onto it from the Kinect's nominal RGB camera (focal length 525 px, same principal point; the RGB focal
length Brachmann et al. use for 7-Scenes): an approximate registration that removes the 585/525 difference in
scale (up to ~35 px at the image corners) but not the ~2.5 cm baseline between the two sensors (a parallax of
about 585 * 0.025 / z px, ~7 px at 2 m). `color_camera=None` keeps the colour as recorded and uses the depth
intrinsics for both, the common practice. Timestamps are frame number / 30 (the Kinect's rate). Pose files may
all be absent (no ground truth); when any is present every frame needs one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from .base import Frame
from .scannet import ResampleColor, ResampledSequence, partner, read_pose_txt

SEVENSCENES_CAMERA = PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)  # depth camera, published
SEVENSCENES_COLOR_CAMERA = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)  # nominal Kinect RGB, approximate
SEVENSCENES_DEPTH_SCALE = 1000.0
SEVENSCENES_INVALID_DEPTH = 65535
SEVENSCENES_FPS = 30.0
_COLOR_SUFFIXES = (".color.png", ".color.jpg")


def is_sevenscenes_sequence(path: Path) -> bool:
    return path.is_dir() and next(path.glob("frame-*.depth.png"), None) is not None and \
        any(next(path.glob(f"frame-*{s}"), None) is not None for s in _COLOR_SUFFIXES)


class SevenScenesSequence(ResampledSequence):
    """An `ImageSequence` whose depth value 65535 (7-Scenes' "no measurement") reads as 0."""

    def __getitem__(self, i: int) -> Frame:
        f = super().__getitem__(i)
        f.depth[f.depth >= np.float32(SEVENSCENES_INVALID_DEPTH) / np.float32(self.depth_scale)] = 0.0
        return f


def _frames(root: Path) -> list[tuple[int, str, Path]]:
    """(frame number, 'frame-NNNNNN', colour file) in frame order."""
    out = []
    for p in root.iterdir():
        suffix = next((s for s in _COLOR_SUFFIXES if p.name.endswith(s)), None)
        if suffix is None or not p.name.startswith("frame-"):
            continue
        stem = p.name[: -len(suffix)]
        if not stem[6:].isdigit():
            raise InputError(f"{p}: 7-Scenes frames are named frame-NNNNNN.color.png")
        out.append((int(stem[6:]), stem, p))
    if not out:
        raise InputError(f"{root}: no frame-NNNNNN.color.png images")
    return sorted(out)


def load_sevenscenes_sequence(path: str | Path, *, camera: PinholeCamera = SEVENSCENES_CAMERA,
                              color_camera: PinholeCamera | None = SEVENSCENES_COLOR_CAMERA, name: str | None = None,
                              fps: float = SEVENSCENES_FPS) -> SevenScenesSequence:
    """Load one 7-Scenes `seq-NN/` folder. `camera` is the depth camera every frame is given; `color_camera` the
    camera the colour images were taken with (resampled onto `camera`), or None to use them as recorded."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    frames = _frames(root)
    names = {p.name for p in root.iterdir()}
    depth = [partner(root, stem + ".depth.png", c.name, "depth", names) for _, stem, c in frames]
    poses = None
    if any(n.endswith(".pose.txt") for n in names):
        poses = np.stack([read_pose_txt(partner(root, stem + ".pose.txt", c.name, "pose", names))
                          for _, stem, c in frames])
    transform = None
    if color_camera is not None and color_camera != camera:
        transform = ResampleColor(color_camera, camera, "the colour camera's size")
    stamps = np.array([k for k, _, _ in frames], dtype=np.float64) / fps
    return SevenScenesSequence(name=name or root.name, root=root, camera=camera, timestamps=stamps,
                               color_paths=[c for _, _, c in frames], depth_paths=depth,
                               depth_scale=SEVENSCENES_DEPTH_SCALE, gt_poses=poses, color_transform=transform)
