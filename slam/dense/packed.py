"""Keyframe images kept losslessly compressed between uses: colour as PNG, depth as 16-bit PNG. A retired
submap's keyframes are only read again by loop-closure registration and the map refinement, so they wait packed
(2-3x smaller at 320 and 160 pixels wide) and are decoded on each read, bit for bit the frame that was packed
(about 2 ms for a 160x120 copy). The active submap's keyframes stay raw: mapping reads them on every keyframe.
The process's peak is not lowered by this alone: the final refinement holds every keyframe's views as float32
tensors at once (slam.dense.mapping.refine)."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from swarmsplat.kernels.camera import PinholeCamera

from .frames import RGBD

_MM = np.float32(1000.0)


class PackedRGBD:
    """An RGBD frame stored as PNG bytes; reads like RGBD (`color`, `depth`, `camera`, the tensor helpers), each
    read decoding anew. Depth is stored as millimetres (uint16) when `mm / 1000` gives back every float32 exactly
    (frames straight from a millimetre sensor), else as the float32's bits, high and low 16-bit halves side by
    side, so the round trip is exact either way."""

    __slots__ = ("camera", "_color_png", "_depth_png", "_depth_mm")

    def __init__(self, frame: RGBD):
        self.camera: PinholeCamera = frame.camera
        self._color_png = _encode(cv2.cvtColor(np.ascontiguousarray(frame.color), cv2.COLOR_RGB2BGR))
        depth = np.ascontiguousarray(frame.depth, dtype=np.float32)  # [H, W] metres
        mm = np.rint(depth.astype(np.float64) * 1000.0)
        self._depth_mm = bool(mm.max(initial=0.0) <= 65535 and np.array_equal(_from_mm(mm), depth.view(np.uint32)))
        if self._depth_mm:
            self._depth_png = _encode(mm.astype(np.uint16))
        else:
            bits = depth.view(np.uint32)
            self._depth_png = _encode(np.concatenate([(bits >> 16).astype(np.uint16),
                                                      (bits & 0xFFFF).astype(np.uint16)], axis=1))

    @classmethod
    def from_png(cls, camera: PinholeCamera, color_png: bytes, depth_png: bytes, depth_mm: bool) -> "PackedRGBD":
        """A packed frame from the bytes `png()` gave (another process's keyframe, slam.run.team_link)."""
        out = cls.__new__(cls)
        out.camera, out._color_png, out._depth_png, out._depth_mm = camera, bytes(color_png), bytes(depth_png), \
            bool(depth_mm)
        return out

    def png(self) -> tuple[bytes, bytes, bool]:
        """(colour PNG, depth PNG, depth in millimetres?): what `from_png` takes back."""
        return self._color_png, self._depth_png, self._depth_mm

    @property
    def color(self) -> np.ndarray:  # [H, W, 3] uint8 RGB
        return cv2.cvtColor(_decode(self._color_png), cv2.COLOR_BGR2RGB)

    @property
    def depth(self) -> np.ndarray:  # [H, W] float32 metres, 0 = invalid
        planes = _decode(self._depth_png)
        if self._depth_mm:
            return _from_mm(planes).view(np.float32)
        w = planes.shape[1] // 2
        bits = (planes[:, :w].astype(np.uint32) << 16) | planes[:, w:].astype(np.uint32)
        return bits.view(np.float32)

    @property
    def nbytes(self) -> int:
        return len(self._color_png) + len(self._depth_png)

    def unpacked(self) -> RGBD:
        return RGBD(self.color, self.depth, self.camera)

    def resized(self, max_width: int) -> RGBD:
        return self.unpacked().resized(max_width)

    def color_tensor(self, device="cpu") -> torch.Tensor:  # [H, W, 3] float32 in [0, 1]
        return self.unpacked().color_tensor(device)

    def depth_tensor(self, device="cpu") -> torch.Tensor:  # [H, W] float32 metres
        return self.unpacked().depth_tensor(device)

    def valid_fraction(self) -> float:
        return self.unpacked().valid_fraction()


def pack_lossy(frame: RGBD | PackedRGBD, quality: int = 90) -> PackedRGBD:
    """`frame` compressed for a link, not losslessly: colour as JPEG at `quality`, depth rounded to millimetres
    (16-bit PNG). Reads like any PackedRGBD.

    The JPEG keeps full-resolution chroma (4:4:4): the usual 4:2:0 halves the colour resolution, which on
    colourful fine texture costs more than the quality setting (the demo's frames at q90: 29.4 dB from the
    original with 4:2:0, 34.0 dB with 4:4:4, for 33 against 46 kB at 320x240; Redwood 211: 37.7 against 39.7 dB)."""
    depth = np.asarray(frame.depth, dtype=np.float64)
    mm = np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(frame.color), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality),
                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
    if not ok:
        raise RuntimeError(f"JPEG encoding failed for an image {list(frame.color.shape)}")
    return PackedRGBD.from_png(frame.camera, jpg.tobytes(), _encode(mm), True)


def pack(frame: RGBD | PackedRGBD | None) -> RGBD | PackedRGBD | None:
    """`frame` packed (None and packed frames pass through)."""
    return frame if frame is None or isinstance(frame, PackedRGBD) else PackedRGBD(frame)


def _from_mm(mm: np.ndarray) -> np.ndarray:  # the float32 bits of mm / 1000, as uint32
    return (mm.astype(np.float32) / _MM).astype(np.float32).view(np.uint32)


def _encode(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError(f"PNG encoding failed for an image {img.dtype} {list(img.shape)}")
    return buf.tobytes()


def _decode(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
