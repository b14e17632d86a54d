"""EuRoC MAV (ASL layout) as a monocular sequence: left camera images, ground truth moved to the camera.

    <seq>/mav0/cam0/data.csv               '#timestamp [ns],filename'
    <seq>/mav0/cam0/data/<ns>.png          752x480 greyscale (returned as RGB by replication)
    <seq>/mav0/cam0/sensor.yaml            T_BS (camera -> body), intrinsics [fu fv cu cv], resolution,
                                           radial-tangential distortion
    <seq>/mav0/state_groundtruth_estimate0/data.csv   T_world_body at 200 Hz

T_world_cam = T_world_body @ T_body_cam. Images are undistorted to the pinhole camera with the same K (so
`camera` is exact), unless `undistort=False`. Frames with no ground-truth sample within 10 ms (the start of
each recording) get a NaN pose row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import is_file
from swarmsplat.slam.io.trajectory import read_euroc_csv

from ._sequence import ImageSequence, poses_at
from .base import MultiAgentDataset

GT_MAX_DIFF = 0.01


def _mav0(path: Path) -> Path:
    return path if path.name == "mav0" else path / "mav0"


def is_euroc_sequence(path: Path) -> bool:
    return (_mav0(path) / "cam0" / "data.csv").is_file()


def read_sensor_yaml(path: Path) -> tuple[PinholeCamera, np.ndarray, np.ndarray]:
    """-> (camera, distortion [k1 k2 p1 p2], T_body_cam [4, 4]). EuRoC files start with an OpenCV
    '%YAML:1.0' directive PyYAML refuses, so directive lines are skipped."""
    import yaml

    if not path.is_file():
        raise InputError(f"camera description not found: {path}")
    text = "\n".join(l for l in path.read_text().splitlines() if not l.startswith("%"))
    try:
        d = yaml.safe_load(text)
        T = np.asarray(d["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
        fu, fv, cu, cv = (float(v) for v in d["intrinsics"])
        w, h = (int(v) for v in d["resolution"])
        dist = np.asarray(d.get("distortion_coefficients", [0, 0, 0, 0]), dtype=np.float64)
        model = d.get("distortion_model", "radial-tangential")
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: not a EuRoC sensor.yaml (T_BS, intrinsics, resolution): {e}") from None
    if model != "radial-tangential":
        raise InputError(f"{path}: distortion model {model!r} not supported (expected radial-tangential)")
    return PinholeCamera(fu, fv, cu, cv, w, h), dist, T


def _read_cam_csv(path: Path) -> tuple[np.ndarray, list[Path]]:
    if not path.is_file():
        raise InputError(f"image list not found: {path}")
    stamps, files = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 2:
            raise InputError(f"{path}:{lineno}: expected 'timestamp_ns,filename', got {len(parts)} fields")
        try:
            t = int(parts[0]) * 1e-9
        except ValueError:
            raise InputError(f"{path}:{lineno}: timestamp is not an integer of nanoseconds: {parts[0]!r}") from None
        f = path.parent / "data" / parts[1]
        if not is_file(f, f"{path}:{lineno}"):
            raise InputError(f"{path}:{lineno}: listed image not found: {f}")
        stamps.append(t)
        files.append(f)
    if not files:
        raise InputError(f"{path}: lists no images")
    return np.asarray(stamps), files


class _Undistort:
    """Remaps distorted images onto the same pinhole K; maps built on first use (cheap, once per sequence)."""

    def __init__(self, cam: PinholeCamera, dist: np.ndarray):
        self.cam, self.dist, self.maps = cam, dist, None

    def __call__(self, img: np.ndarray) -> np.ndarray:
        import cv2

        if self.maps is None:
            self.maps = cv2.initUndistortRectifyMap(self.cam.K, self.dist, None, self.cam.K,
                                                    (self.cam.width, self.cam.height), cv2.CV_32FC1)
        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR)


def load_euroc_sequence(path: str | Path, *, camera: str = "cam0", undistort: bool = True,
                        name: str | None = None) -> ImageSequence:
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    mav = _mav0(root)
    cam_dir = mav / camera
    cam, dist, T_body_cam = read_sensor_yaml(cam_dir / "sensor.yaml")
    t, files = _read_cam_csv(cam_dir / "data.csv")
    gt = None
    gt_file = mav / "state_groundtruth_estimate0" / "data.csv"
    if gt_file.is_file():
        t_gt, T_world_body = read_euroc_csv(gt_file)
        gt = poses_at(t, t_gt, T_world_body, GT_MAX_DIFF) @ T_body_cam
    transform = _Undistort(cam, dist) if undistort and np.any(dist != 0) else None
    seq_name = name or (root.parent.name if root.name == "mav0" else root.name)
    return ImageSequence(name=seq_name, root=root, camera=cam, timestamps=t, color_paths=files, gt_poses=gt,
                         color_transform=transform)


def load_euroc_collection(path: str | Path, **kw) -> MultiAgentDataset:
    """A folder of EuRoC sequences (e.g. MH_01 ... MH_05) as a monocular team, one agent per sequence."""
    root = Path(path)
    dirs = [d for d in sorted(root.iterdir()) if d.is_dir() and is_euroc_sequence(d)]
    if not dirs:
        raise InputError(f"{root}: no EuRoC sequences (folders with mav0/cam0/data.csv)")
    return MultiAgentDataset(root=root, agents=[load_euroc_sequence(d, **kw) for d in dirs], name=root.name,
                             kind="mono", meta={"layout": "euroc"})
