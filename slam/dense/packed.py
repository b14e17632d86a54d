"""Keyframe images kept losslessly compressed between uses: colour as PNG, depth as 16-bit PNG. A retired
submap's keyframes are only read again by loop-closure registration and the map refinement, so they wait packed
(2-3x smaller at 320 and 160 pixels wide) and are decoded on each read, bit for bit the frame that was packed
(about 2 ms for a 160x120 copy). The active submap's keyframes stay raw: mapping reads them on every keyframe.

A packed frame can also leave memory (`PackedRGBD.store`): its bytes go to a store (a run folder's
keyframes/*/NNNN.bin, slam.io.submap_files) and are read back at each use, so a long mission keeps a few hundred
bytes per keyframe in memory instead of the ~0.4 MB of its two packed copies."""

from __future__ import annotations

import struct

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

    __slots__ = ("camera", "_color_png", "_depth_png", "_depth_mm", "_stored")

    def __init__(self, frame: RGBD):
        self.camera: PinholeCamera = frame.camera
        self._stored = None  # (store, key) once `store` moved the bytes out of memory
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
        out._stored = None
        return out

    def png(self) -> tuple[bytes, bytes, bool]:
        """(colour PNG, depth PNG, depth in millimetres?): what `from_png` takes back."""
        stored = getattr(self, "_stored", None)  # None in frames pickled before frames could be stored
        if stored is None:
            return self._color_png, self._depth_png, self._depth_mm
        store, key = stored
        return _unframe(store.read(key), store.describe(key))

    def store(self, store, key: int) -> None:
        """Write the packed bytes to `store` (anything with write(key, bytes), read(key) and describe(key):
        slam.io.submap_files.SubmapFiles) under `key` and drop them from memory; reads then load them from there.
        A frame stored already stays where it is."""
        if getattr(self, "_stored", None) is not None:
            return
        c, d, mm = self.png()
        store.write(key, _frame_bytes(c, d, mm))
        self._stored, self._color_png, self._depth_png = (store, int(key)), b"", b""

    @property
    def stored(self) -> bool:
        """Whether the bytes live in a store rather than in memory."""
        return getattr(self, "_stored", None) is not None

    @property
    def color(self) -> np.ndarray:  # [H, W, 3] uint8 RGB
        return cv2.cvtColor(_decode(self.png()[0]), cv2.COLOR_BGR2RGB)

    @property
    def depth(self) -> np.ndarray:  # [H, W] float32 metres, 0 = invalid
        return _depth_of(_decode(self.png()[1]), self._depth_mm)

    @property
    def nbytes(self) -> int:
        """Bytes of the packed images (wherever they are kept)."""
        c, d, _ = self.png()
        return len(c) + len(d)

    def unpacked(self) -> RGBD:
        c, d, mm = self.png()
        return RGBD(cv2.cvtColor(_decode(c), cv2.COLOR_BGR2RGB), _depth_of(_decode(d), mm), self.camera)

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


def _depth_of(planes: np.ndarray, depth_mm: bool) -> np.ndarray:
    """[H, W] float32 metres from the decoded depth PNG (see PackedRGBD)."""
    if depth_mm:
        return _from_mm(planes).view(np.float32)
    w = planes.shape[1] // 2
    bits = (planes[:, :w].astype(np.uint32) << 16) | planes[:, w:].astype(np.uint32)
    return bits.view(np.float32)


_MAGIC = b"SSKF"
_HEAD = struct.Struct("<4sBBII")  # magic, version, depth in millimetres, colour bytes, depth bytes


def _frame_bytes(color_png: bytes, depth_png: bytes, depth_mm: bool) -> bytes:
    """A stored frame's file: a header, then the colour and the depth PNG."""
    return _HEAD.pack(_MAGIC, 1, int(depth_mm), len(color_png), len(depth_png)) + color_png + depth_png


def _unframe(data: bytes, source: str) -> tuple[bytes, bytes, bool]:
    """(colour PNG, depth PNG, depth in millimetres?) of `_frame_bytes`'s file; InputError naming `source` when
    the bytes are not one."""
    from swarmsplat.kernels.errors import InputError

    if len(data) < _HEAD.size:
        raise InputError(f"{source}: {len(data)} bytes, too short for a stored keyframe")
    magic, version, mm, nc, nd = _HEAD.unpack_from(data)
    if magic != _MAGIC or version != 1 or len(data) != _HEAD.size + nc + nd:
        raise InputError(f"{source}: not a stored keyframe (expected {_MAGIC!r} version 1 with {nc} + {nd} bytes of "
                         f"PNG, got {magic!r} version {version}, {len(data)} bytes)")
    at = _HEAD.size
    return data[at:at + nc], data[at + nc:], bool(mm)


def _from_mm(mm: np.ndarray) -> np.ndarray:  # the float32 bits of mm / 1000, as uint32
    return (mm.astype(np.float32) / _MM).astype(np.float32).view(np.uint32)


def _encode(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError(f"PNG encoding failed for an image {img.dtype} {list(img.shape)}")
    return buf.tobytes()


def _decode(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
