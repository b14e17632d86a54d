"""Our folder format (what `swarmsplat generate` writes), one agent per folder:

    rgb/ depth/            8-bit RGB PNGs; uint16 depth PNGs (metres = value / depth_scale)
    rgb.txt depth.txt      TUM lists: '# comment' lines, then 'timestamp relative/path.png' per frame
    groundtruth.txt        TUM 't x y z qx qy qz qw', T_world_cam (optional)
    calibration.yaml       fx fy cx cy width height [depth_scale]
A monocular sequence has rgb/, rgb.txt, odometry.txt (TUM, metric odometry T_world_cam in the odometry frame),
optional groundtruth.txt and calibration.yaml (no depth_scale). A multi-agent dataset is a root folder with
`dataset.yaml` ({name, kind: rgbd|mono, agents: [folder, ...]}, extra keys kept in `meta`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import is_file, text_lines
from swarmsplat.slam.io.trajectory import read_tum

from ._sequence import ImageSequence, poses_at
from .base import MultiAgentDataset

# RGB and depth of one frame share a stamp in our format; GT/odometry stamps are taken within this tolerance.
POSE_MAX_DIFF = 0.01
PAIR_MAX_DIFF = 0.02


def read_image_list(path: str | Path) -> tuple[np.ndarray, list[Path]]:
    """Read a TUM image list ('timestamp relative/path' lines, '#' comments) -> (stamps [N], absolute paths).

    Every listed file must exist; errors name file:line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image list not found: {path}")
    stamps, files = [], []
    for lineno, line in text_lines(path, "image list"):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 2:
            raise InputError(f"{path}:{lineno}: expected 'timestamp relative/path', got {len(parts)} fields")
        try:
            t = float(parts[0])
        except ValueError:
            raise InputError(f"{path}:{lineno}: timestamp is not a number: {parts[0]!r}") from None
        if not math.isfinite(t):
            raise InputError(f"{path}:{lineno}: timestamp is NaN or Inf")
        img = path.parent / parts[1]
        if not is_file(img, f"{path}:{lineno}"):
            raise InputError(f"{path}:{lineno}: listed image not found: {img}")
        stamps.append(t)
        files.append(img)
    if not files:
        raise InputError(f"{path}: lists no images")
    return np.asarray(stamps), files


def _read_yaml_mapping(path: Path, what: str, keys: str) -> dict:
    """A YAML file that must hold a mapping; InputError naming the file for a missing file, bad YAML or wrong shape."""
    import yaml

    if not path.is_file():
        raise InputError(f"{what} not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        raise InputError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text YAML file (bytes that are not UTF-8 text)") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping with keys {keys}")
    return data


def read_calibration(path: str | Path, *, need_depth_scale: bool) -> tuple[PinholeCamera, float | None]:
    """calibration.yaml -> (camera, depth_scale or None)."""
    path = Path(path)
    data = _read_yaml_mapping(path, "calibration file", "fx fy cx cy width height [depth_scale]")
    keys = ["fx", "fy", "cx", "cy", "width", "height"] + (["depth_scale"] if need_depth_scale else [])
    missing = [k for k in keys if k not in data]
    if missing:
        raise InputError(f"{path}: missing key(s) {', '.join(missing)}")
    vals = {}
    for k in keys + (["depth_scale"] if "depth_scale" in data and not need_depth_scale else []):
        try:
            vals[k] = float(data[k])
        except (TypeError, ValueError):
            raise InputError(f"{path}: field '{k}' must be a number, got {data[k]!r}") from None
        if not math.isfinite(vals[k]):
            raise InputError(f"{path}: field '{k}' is not finite")
    for k in ("width", "height"):
        if vals[k] != int(vals[k]) or vals[k] <= 0:
            raise InputError(f"{path}: field '{k}' must be a positive integer, got {data[k]!r}")
    scale = vals.get("depth_scale")
    if scale is not None and scale <= 0:
        raise InputError(f"{path}: field 'depth_scale' must be positive, got {data['depth_scale']!r}")
    try:
        cam = PinholeCamera(vals["fx"], vals["fy"], vals["cx"], vals["cy"], int(vals["width"]), int(vals["height"]))
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    return cam, scale


def is_folder_sequence(path: Path) -> bool:
    return (path / "calibration.yaml").is_file() and (path / "rgb.txt").is_file()


def load_folder_sequence(path: str | Path, name: str | None = None) -> ImageSequence:
    """Load one agent folder of our format (RGB-D when depth.txt exists, else monocular with odometry.txt)."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    rgbd = (root / "depth.txt").is_file()
    if not rgbd and not (root / "odometry.txt").is_file():
        raise InputError(f"{root}: neither depth.txt (RGB-D) nor odometry.txt (monocular) found")
    cam, depth_scale = read_calibration(root / "calibration.yaml", need_depth_scale=rgbd)
    t_rgb, rgb = read_image_list(root / "rgb.txt")
    depth = None
    if rgbd:
        t_d, depth = read_image_list(root / "depth.txt")
        if len(depth) != len(rgb):
            raise InputError(f"{root}: rgb.txt lists {len(rgb)} frames but depth.txt lists {len(depth)}")
        far = np.nonzero(np.abs(t_d - t_rgb) > PAIR_MAX_DIFF)[0]
        if len(far):
            k = int(far[0])
            raise InputError(f"{root}: frame {k} has RGB stamp {t_rgb[k]:.6f} but depth stamp {t_d[k]:.6f} "
                             f"(rgb.txt and depth.txt must list the same frames in the same order)")
    gt = _poses_file(root / "groundtruth.txt", t_rgb)
    odom = _poses_file(root / "odometry.txt", t_rgb)
    return ImageSequence(name=name or root.name, root=root, camera=cam, timestamps=t_rgb, color_paths=rgb,
                         depth_paths=depth, depth_scale=depth_scale, gt_poses=gt, odometry=odom)


def _poses_file(path: Path, stamps: np.ndarray) -> np.ndarray | None:
    if not path.is_file():
        return None
    t, T = read_tum(path)
    return poses_at(stamps, t, T, POSE_MAX_DIFF)


def load_folder_dataset(root: str | Path, load_agent=None) -> MultiAgentDataset:
    """Load a multi-agent root folder described by `dataset.yaml`. `load_agent(folder)`: loads one agent folder
    (slam.io.datasets.load_dataset passes one that reads any single-sequence layout); default: our format."""
    root = Path(root)
    meta_path = root / "dataset.yaml"
    meta = _read_yaml_mapping(meta_path, "dataset description", "name, kind, agents")
    agents = meta.get("agents")
    if not isinstance(agents, list) or not agents or not all(isinstance(a, str) and a for a in agents):
        raise InputError(f"{meta_path}: 'agents' must be a non-empty list of folder names")
    if len(set(agents)) != len(agents):
        raise InputError(f"{meta_path}: 'agents' names a folder twice")
    kind = str(meta.get("kind", "rgbd"))
    if kind not in ("rgbd", "mono"):
        raise InputError(f"{meta_path}: 'kind' must be rgbd or mono, got {kind!r}")
    seqs = []
    for a in agents:
        folder = root / a
        if not is_file(folder, f"{meta_path}: agents", folder=True):
            raise InputError(f"{meta_path}: agent folder not found: {folder}")
        seq = (load_agent or load_folder_sequence)(folder)
        if (kind == "rgbd") != seq.is_rgbd:
            raise InputError(f"{folder}: dataset.yaml says kind '{kind}' but this folder is "
                             f"{'RGB-D' if seq.is_rgbd else 'monocular'}")
        seqs.append(seq)
    extra = {k: v for k, v in meta.items() if k not in ("name", "kind", "agents")}
    return MultiAgentDataset(root=root, agents=seqs, name=str(meta.get("name", root.name)), kind=kind, meta=extra)
