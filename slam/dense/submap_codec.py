"""The compact form of a finished submap's Gaussians: quantised, entropy-coded bytes with a versioned header.

A finished submap is no longer optimised until the final map refinement, so its Gaussians can be kept (in memory,
in the run folder, on the team link) in far fewer bytes than the optimiser's float32 (56 bytes each):

  means            uint16 per axis, uniform within the submap's bounding box (local frame)
  log_scales       uint8 or uint16, uniform within the submap's [min, max] log scale
  quats            uint8 or uint16 per wxyz component of the unit quaternion (w >= 0: the same rotation)
  opacities        uint8 or uint16 of sigmoid(logit) in [0, 1]
  colors           uint8 or uint16 of RGB clamped to [0, 1] (the rasteriser clamps them anyway)

Every quantity is rounded to the nearest of 2^bits - 1 equal steps over its range, so a decoded value is within
half a step of the encoded one (`error_bounds`). The 16-bit arrays are stored high bytes then low bytes, which
zlib / lzma compress better than interleaved bytes. Layout (little-endian):

  header  magic "SSGC", format version, codec (0 raw, 1 zlib, 2 lzma), N, bits of the five quantities,
          means' box lo/hi [3] + [3] and log-scale lo/hi (float64), payload length, CRC-32 of the payload
  payload the quantised arrays in the order above, then compressed

    blob = encode(params, CodecSpec())
    params = decode(blob, source="submaps/0003.bin")
"""

from __future__ import annotations

import functools
import lzma
import struct
import zlib
from dataclasses import dataclass

import numpy as np
import torch

from swarmsplat.kernels.errors import InputError

from .gaussian_map import GaussianParams

MAGIC = b"SSGC"
VERSION = 1
_HEADER = struct.Struct("<4sHBxI5B3x8d2I")  # magic, version, codec, n, bits x5, lo/hi means, lo/hi scales, len, crc
_CODECS = {"none": 0, "zlib": 1, "lzma": 2}
_QUANTITIES = ("means", "log_scales", "quats", "opacities", "colors")
_WIDTH = {"means": 3, "log_scales": 3, "quats": 4, "opacities": 1, "colors": 3}


class CodecError(InputError):
    """Bytes that are not a compact submap this version reads (corrupt, truncated, foreign or newer)."""


@dataclass(frozen=True)
class CodecSpec:
    """Bits per quantity (8 or 16; means always 16) and the entropy coder ('none', 'zlib', 'lzma')."""

    scale_bits: int = 8
    quat_bits: int = 8
    opacity_bits: int = 8
    color_bits: int = 8
    compression: str = "zlib"
    exact: bool = False  # the optimiser's float32 parameters bit for bit instead (bits recorded as 32)

    def bits(self) -> tuple[int, ...]:
        if self.exact:
            return (32,) * 5
        return (16, self.scale_bits, self.quat_bits, self.opacity_bits, self.color_bits)


EXACT = CodecSpec(exact=True)


def _steps(bits: int) -> int:
    return (1 << bits) - 1


def _ranges(params: GaussianParams) -> tuple[np.ndarray, np.ndarray, float, float]:
    m = params.means.detach().double().cpu().numpy()
    s = params.log_scales.detach().double().cpu().numpy()
    if len(m) == 0:
        return np.zeros(3), np.zeros(3), 0.0, 0.0
    return m.min(0), m.max(0), float(s.min()), float(s.max())


def _unit(params: GaussianParams) -> dict[str, np.ndarray]:
    """Each quantity as float64 [N, k] in its coding range's units (before the affine map to [0, 1])."""
    p = params.detached()
    q = p.quats.double()
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-30)
    q = torch.where(q[:, :1] < 0, -q, q)
    return {"means": p.means.double().numpy(), "log_scales": p.log_scales.double().numpy(),
            "quats": q.numpy(), "opacities": torch.sigmoid(p.logit_opacities.double())[:, None].numpy(),
            "colors": p.colors.double().clamp(0.0, 1.0).numpy()}


def _affine(name: str, lo_m, hi_m, lo_s, hi_s) -> tuple[np.ndarray, np.ndarray]:
    """(lo, span) of a quantity's coding range."""
    if name == "means":
        return np.asarray(lo_m), np.asarray(hi_m) - np.asarray(lo_m)
    if name == "log_scales":
        return np.array([lo_s]), np.array([hi_s - lo_s])
    if name == "quats":
        return np.array([-1.0]), np.array([2.0])
    return np.array([0.0]), np.array([1.0])


def error_bounds(params: GaussianParams, spec: CodecSpec = CodecSpec()) -> dict[str, np.ndarray]:
    """The largest decoding error of each quantity for `params` under `spec`: half a quantisation step of its
    range (means per axis [3], the rest one scalar), in the quantity's units (opacity, not its logit; the unit
    quaternion with w >= 0). Float32 rounding of the decoded values comes on top."""
    lo_m, hi_m, lo_s, hi_s = _ranges(params)
    return {name: _affine(name, lo_m, hi_m, lo_s, hi_s)[1] / _steps(b) / 2.0
            for name, b in zip(_QUANTITIES, spec.bits())}


def _planes(a: np.ndarray) -> bytes:
    """uint8 as is; uint16 as all high bytes, then all low bytes."""
    if a.dtype == np.uint8:
        return a.tobytes()
    return (a >> 8).astype(np.uint8).tobytes() + (a & 0xFF).astype(np.uint8).tobytes()


def encode(params: GaussianParams, spec: CodecSpec = CodecSpec()) -> bytes:
    """The compact form of `params` (any N, float tensors on any device)."""
    if not spec.exact and any(b not in (8, 16) for b in spec.bits()):
        raise InputError(f"submap codec: bits must be 8 or 16, got {list(spec.bits())}")
    if spec.compression not in _CODECS:
        raise InputError(f"submap codec: compression must be one of {sorted(_CODECS)}, got {spec.compression!r}")
    n = len(params)
    lo_m, hi_m, lo_s, hi_s = _ranges(params)
    chunks = []
    if spec.exact:
        chunks = [t.detach().cpu().to(torch.float32).contiguous().numpy().tobytes() for t in params.tensors()]
    unit = {} if spec.exact else _unit(params)
    for name, b in zip(_QUANTITIES, () if spec.exact else spec.bits()):
        lo, span = _affine(name, lo_m, hi_m, lo_s, hi_s)
        steps = _steps(b)
        x = (unit[name] - lo) / np.where(span > 0, span, 1.0)
        q = np.rint(np.clip(x, 0.0, 1.0) * steps).astype(np.uint16 if b == 16 else np.uint8)
        chunks.append(_planes(q.reshape(n, _WIDTH[name])))
    raw = b"".join(chunks)
    body = {"none": lambda d: d, "zlib": lambda d: zlib.compress(d, 6),
            "lzma": lambda d: lzma.compress(d, preset=6)}[spec.compression](raw)
    header = _HEADER.pack(MAGIC, VERSION, _CODECS[spec.compression], n, *spec.bits(), *lo_m, *hi_m, lo_s, hi_s,
                          len(body), zlib.crc32(body))
    return header + body


def decode(blob: bytes, *, source: str = "compact submap") -> GaussianParams:
    """GaussianParams (float32, CPU) from `encode`'s bytes; CodecError naming `source` and what was expected when
    the bytes are not such a blob."""
    blob = bytes(blob)
    if len(blob) < _HEADER.size or blob[:4] != MAGIC:
        raise CodecError(f"{source}: not a compact submap (expected {_HEADER.size}+ bytes starting with "
                         f"{MAGIC!r}, got {len(blob)} bytes starting with {blob[:4]!r})")
    magic, version, codec, n, *rest = _HEADER.unpack_from(blob)
    bits, box, (length, crc) = rest[:5], rest[5:13], rest[13:]
    if version != VERSION:
        raise CodecError(f"{source}: compact submap format version {version}, this version reads {VERSION}")
    exact = all(b == 32 for b in bits)
    if codec not in _CODECS.values() or not (exact or all(b in (8, 16) for b in bits)):
        raise CodecError(f"{source}: unknown codec {codec} or bits {list(bits)} (expected codec 0-2, bits 8/16 "
                         f"or all 32)")
    body = blob[_HEADER.size:]
    if len(body) != length or zlib.crc32(body) != crc:
        raise CodecError(f"{source}: corrupt compact submap (expected a {length}-byte payload with CRC-32 "
                         f"{crc:08x}, got {len(body)} bytes with CRC-32 {zlib.crc32(body):08x})")
    try:
        raw = {0: lambda d: d, 1: zlib.decompress, 2: lzma.decompress}[codec](body)
    except (zlib.error, lzma.LZMAError) as e:
        raise CodecError(f"{source}: corrupt compact submap payload ({e})") from None
    lo_m, hi_m, lo_s, hi_s = np.array(box[0:3]), np.array(box[3:6]), box[6], box[7]
    want = sum(n * _WIDTH[name] * b // 8 for name, b in zip(_QUANTITIES, bits))
    if len(raw) != want:
        raise CodecError(f"{source}: payload of {len(raw)} bytes, expected {want} for {n} Gaussians")
    t = lambda a: torch.from_numpy(np.array(a, dtype=np.float32, order="C"))  # noqa: E731
    if exact:
        a = np.frombuffer(raw, np.float32)
        cut = np.cumsum([0] + [n * _WIDTH[name] for name in _QUANTITIES])
        m, s, q, o, c = (a[i:j].reshape(n, _WIDTH[name]) for i, j, name in zip(cut[:-1], cut[1:], _QUANTITIES))
        return GaussianParams(t(m), t(s), t(q), t(o[:, 0]), t(c))
    out, at = {}, 0
    for name, b in zip(_QUANTITIES, bits):
        k = n * _WIDTH[name]
        if b == 8:
            q = np.frombuffer(raw, np.uint8, k, at).astype(np.float64)
        else:
            hi = np.frombuffer(raw, np.uint8, k, at).astype(np.uint16)
            q = ((hi << 8) | np.frombuffer(raw, np.uint8, k, at + k)).astype(np.float64)
        at += k * b // 8
        lo, span = _affine(name, lo_m, hi_m, lo_s, hi_s)
        out[name] = lo + q.reshape(n, _WIDTH[name]) / _steps(b) * span
    half = 0.5 / _steps(bits[3])  # opacities 0 and 1 have no finite logit: stay within half a step of them
    o = np.clip(out["opacities"][:, 0], half, 1.0 - half)
    return GaussianParams(t(out["means"]), t(out["log_scales"]), t(out["quats"]), t(np.log(o / (1.0 - o))),
                          t(out["colors"]))


class MemoryStore:
    """Finished submaps' bytes kept in memory (a run without an output folder); pickles with them."""

    def __init__(self):
        self.blobs: dict[int, bytes] = {}

    def write(self, key: int, data: bytes) -> None:
        self.blobs[int(key)] = bytes(data)

    def read(self, key: int) -> bytes:
        return self.blobs[int(key)]

    def describe(self, key: int) -> str:
        return f"submap {key} (in memory)"

    def nbytes(self) -> int:
        return sum(len(b) for b in self.blobs.values())


def stored_compact(submap) -> bytes | None:
    """The compact bytes a finished submap (slam.dense.gaussian_map.Submap) is stored as, or None when it is held
    as tensors or stored exactly (float32)."""
    if submap.stored is None:
        return None
    blob = submap.stored.store.read(submap.stored.key)
    return None if blob[:4] != MAGIC or _HEADER.unpack_from(blob)[4] == 32 else blob


def spec_for(storage: str) -> CodecSpec:
    """The form of config `submap.storage`: 'compact' (quantised, zlib) or 'float32' (exact)."""
    return EXACT if storage == "float32" else CodecSpec()


def use_storage(gmap, storage: str, store=None) -> None:
    """Keep `gmap`'s finished submaps (slam.dense.gaussian_map.GaussianMap.retire) in the form `storage` in
    `store` (an object with write / read / describe, e.g. files in the run folder); without a store: 'compact'
    keeps the bytes in memory, 'float32' keeps the tensors as they are."""
    spec = spec_for(storage)
    if store is None and spec.exact:
        gmap.store = gmap.encode = gmap.decode = None
        return
    gmap.store = store if store is not None else MemoryStore()
    gmap.encode = functools.partial(encode, spec=spec)
    gmap.decode = decode
