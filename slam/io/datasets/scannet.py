"""ScanNet scans as ScanNet's SensReader (`reader.py --export_*`) exports them:

    color/0.jpg ...          colour, 1296x968 in ScanNet (frame number names; `--frame_skip` leaves gaps)
    depth/0.png ...          uint16 millimetres, 640x480, 0 = invalid
    pose/0.txt ...           T_world_cam, 4x4 camera-to-world, 4 lines of 4 numbers; '-inf' rows = invalid pose
    intrinsic/intrinsic_color.txt, intrinsic_depth.txt    4x4 (K in the top-left 3x3)
    intrinsic/extrinsic_color.txt, extrinsic_depth.txt    not used (see below)

Frames are given the depth camera: `camera` is `intrinsic_depth.txt` at the depth images' size, and each colour
image is resampled onto it (`ResampleColor`: the depth pixel (u, v) takes the colour seen along its own ray,
K_color K_depth^-1 [u, v, 1]). The colour and depth cameras are treated as sharing their optical centre and axes,
as ScanNet's authors say the exported frames are aligned and no extrinsic should be applied (ScanNet issue #92),
so the extrinsic files are not read. Intrinsics that describe ScanNet's native 1296x968 colour (or 640x480 depth)
are scaled when the images were exported at another size (`reader.py`'s `image_size` leaves them unchanged).
Frames whose pose is invalid get a NaN pose row. Timestamps are frame number / 30 (ScanNet records at 30 Hz).
`pose/` may be absent (no ground truth); when present every frame needs its pose file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import _check_rotation as check_rotation

from ._images import read_color, read_depth
from ._sequence import ImageSequence
from .base import Frame

SCANNET_DEPTH_SCALE = 1000.0
SCANNET_FPS = 30.0
# Native sizes of ScanNet's two cameras (what intrinsic_*.txt describe in every scan).
NATIVE_COLOR_SIZE = (1296, 968)
NATIVE_DEPTH_SIZE = (640, 480)
_COLOR_EXT = (".jpg", ".jpeg", ".png")


def is_scannet_sequence(path: Path) -> bool:
    return all((path / d).is_dir() for d in ("color", "depth", "intrinsic"))


def read_matrix_txt(path: Path, *, allow_invalid: bool = False) -> np.ndarray:
    """A 4x4 matrix written as 4 lines of 4 numbers (np.savetxt) -> [4, 4] float64.

    With `allow_invalid`, a matrix holding any non-finite number (ScanNet writes '-inf' for a frame it could not
    track) gives a NaN matrix; otherwise non-finite numbers are an error.
    """
    if not path.is_file():
        raise InputError(f"file not found: {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            row = [float(v) for v in s.replace(",", " ").split()]
        except ValueError:
            raise InputError(f"{path}:{lineno}: not a number in {s!r}") from None
        if len(row) != 4:
            raise InputError(f"{path}:{lineno}: expected 4 numbers (one row of a 4x4 matrix), got {len(row)}")
        rows.append(row)
    if len(rows) != 4:
        raise InputError(f"{path}: expected a 4x4 matrix (4 lines of 4 numbers), got {len(rows)} lines")
    M = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(M)):
        if allow_invalid:
            return np.full((4, 4), np.nan)
        raise InputError(f"{path}: NaN or Inf in matrix")
    return M


def read_pose_txt(path: Path) -> np.ndarray:
    """T_world_cam [4, 4] from a 4x4 pose file; NaN where the file marks the pose invalid (non-finite numbers)."""
    T = read_matrix_txt(path, allow_invalid=True)
    if np.all(np.isfinite(T)):
        if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
            raise InputError(f"{path}: the last row of a 4x4 pose must be 0 0 0 1")
        check_rotation(path, 1, T)
    return T


def camera_for_images(path: Path, K: np.ndarray, size: tuple[int, int], native: tuple[int, int]) -> PinholeCamera:
    """The pinhole camera of images of `size` (w, h) from the intrinsics K [3, 3] in `path`: K as written when its
    principal point lies near the image centre, else K for the `native` size scaled to `size`."""
    w, h = size
    for cam in (PinholeCamera.from_K(K, w, h), PinholeCamera.from_K(K, *native).scaled(w, h)):
        if abs(cam.cx - (w - 1) / 2) < 0.25 * w and abs(cam.cy - (h - 1) / 2) < 0.25 * h:
            return cam
    raise InputError(f"{path}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) is far from the centre of the {w}x{h} "
                     f"images, also when read as intrinsics of {native[0]}x{native[1]} images")


class ColorSizeError(InputError):
    """A colour image whose size is not the one its camera describes (re-raised by `ResampledSequence` with the
    image's path)."""


class ResampleColor:
    """Resamples a colour image taken with camera `src` onto camera `dst` (same optical centre and axes): pixel
    (u, v) of the result takes the colour along its ray, at K_src K_dst^-1 [u, v, 1] in the source image.

    A much larger source is first area-averaged to about the target size (no aliasing); pixels whose ray leaves the
    source image repeat its border. [Hs, Ws, 3] uint8 -> [Hd, Wd, 3] uint8.
    """

    def __init__(self, src: PinholeCamera, dst: PinholeCamera, why: str = ""):
        self.src, self.dst, self.why = src, dst, why  # why: where the expected source size comes from

    def __call__(self, img: np.ndarray) -> np.ndarray:
        import cv2

        src, dst = self.src, self.dst
        if img.shape[:2] != (src.height, src.width):
            why = f" ({self.why})" if self.why else ""
            raise ColorSizeError(f"colour image is {img.shape[1]}x{img.shape[0]}, expected "
                                 f"{src.width}x{src.height}{why}")
        if src.width > 1.5 * dst.width:
            img = cv2.resize(img, (dst.width, dst.height), interpolation=cv2.INTER_AREA)
            src = src.scaled(dst.width, dst.height)
        M = (src.K @ np.linalg.inv(dst.K))[:2]
        if img.shape[:2] == (dst.height, dst.width) and np.abs(M - np.eye(3)[:2]).max() < 1e-3:
            return img
        return cv2.warpAffine(img, M, (dst.width, dst.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)


class ResampledSequence(ImageSequence):
    """An `ImageSequence` whose colour transform is a `ResampleColor`: a colour image of the wrong size is reported
    with its path."""

    def __getitem__(self, i: int) -> Frame:
        try:
            return super().__getitem__(i)
        except ColorSizeError as e:
            raise InputError(f"{self.color_paths[i]}: {e}") from None


def _frames(root: Path) -> list[tuple[int, Path]]:
    """(frame number, colour file) in frame order; every colour file must be named by its frame number."""
    out = []
    for p in (root / "color").iterdir():
        if p.suffix.lower() not in _COLOR_EXT:
            continue
        if not p.stem.isdigit():
            raise InputError(f"{p}: ScanNet colour frames are named by frame number (color/0.jpg, color/1.jpg, ...)")
        out.append((int(p.stem), p))
    if not out:
        raise InputError(f"{root / 'color'}: no colour images (.jpg)")
    return sorted(out)


def partner(root: Path, rel: str, of: str, what: str, listing: set[str]) -> Path:
    """root / rel, the `what` file of frame file `of`; InputError naming it when its name is not in `listing`."""
    if Path(rel).name not in listing:
        raise InputError(f"{root}: {rel} is missing ({of} has no {what} file)")
    return root / rel


def load_scannet_sequence(path: str | Path, *, name: str | None = None,
                          fps: float = SCANNET_FPS) -> ResampledSequence:
    """Load an exported ScanNet scan folder (see the module docstring) as an RGB-D sequence on the depth camera."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"sequence folder not found: {root}")
    for d in ("color", "depth", "intrinsic"):
        if not (root / d).is_dir():
            raise InputError(f"{root}: ScanNet folder {d}/ is missing")
    intr = root / "intrinsic"
    for f in ("intrinsic_depth.txt", "intrinsic_color.txt"):
        if not (intr / f).is_file():
            raise InputError(f"{root}: intrinsic/{f} is missing")
    frames = _frames(root)
    depth_dir, pose_dir = root / "depth", root / "pose"
    depth_names = {p.name for p in depth_dir.iterdir()}
    pose_names = {p.name for p in pose_dir.iterdir()} if pose_dir.is_dir() else None
    color = [p for _, p in frames]
    depth = [partner(root, f"depth/{p.stem}.png", f"color/{p.name}", "depth", depth_names) for p in color]
    gt = None
    if pose_names is not None:
        gt = np.stack([read_pose_txt(partner(root, f"pose/{p.stem}.txt", f"color/{p.name}", "pose", pose_names))
                       for p in color])
    # The images' sizes fix which resolution the intrinsics are used at; the first frame stands for all.
    d0, c0 = read_depth(depth[0], SCANNET_DEPTH_SCALE), read_color(color[0])
    K_d = read_matrix_txt(intr / "intrinsic_depth.txt")[:3, :3]
    K_c = read_matrix_txt(intr / "intrinsic_color.txt")[:3, :3]
    cam = camera_for_images(intr / "intrinsic_depth.txt", K_d, (d0.shape[1], d0.shape[0]), NATIVE_DEPTH_SIZE)
    cam_c = camera_for_images(intr / "intrinsic_color.txt", K_c, (c0.shape[1], c0.shape[0]), NATIVE_COLOR_SIZE)
    stamps = np.array([k for k, _ in frames], dtype=np.float64) / fps
    return ResampledSequence(name=name or root.name, root=root, camera=cam, timestamps=stamps, color_paths=color,
                             depth_paths=depth, depth_scale=SCANNET_DEPTH_SCALE, gt_poses=gt,
                             color_transform=ResampleColor(cam_c, cam, f"the size of color/{color[0].name}"))
