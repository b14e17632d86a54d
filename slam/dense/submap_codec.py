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

The link form (`for_link`, format version 2) carries the same quantised values in fewer bytes, for a team link
where bytes cost more than time: the Gaussians reordered along a Morton (Z-order) curve of their quantised means,
each mean component delta-coded along that order (wrapping 16-bit differences, zigzag), every quantity's planes
compressed by one lzma stream. Its payload starts with the five quantities' compressed lengths (uint32 each).
Decoding gives exactly the values the stored form decodes to, in the Morton order (on the demo's submaps: 98.8
against 75.7 bits per Gaussian, both with the stored form's bits).

    link_blob = for_link(blob, keep)          # keep: [N] bool, the Gaussians to send (None: all)
    params = decode(link_blob, source="SubmapData")
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
VERSION = 1  # the stored form
LINK_VERSION = 2  # the link form (`for_link`)
MIN_MEAN_BITS = 10  # the link form's coarsest means
_READS = (VERSION, LINK_VERSION)
_HEADER = struct.Struct("<4sHBxI5B3x8d2I")  # magic, version, codec, n, bits x5, lo/hi means, lo/hi scales, len, crc
_CODECS = {"none": 0, "zlib": 1, "lzma": 2}
_LENGTHS = struct.Struct("<5I")  # the link form's compressed length of each quantity
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


def _container(bits: int) -> int:
    """Bytes a quantised value of `bits` is held in (a link form's 14-bit means: 2)."""
    return 1 if bits <= 8 else 2 if bits <= 16 else 4


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


def _parse(blob: bytes, source: str) -> tuple[tuple, bytes]:
    """(header fields, uncompressed payload) of a stored-form or link-form blob; CodecError when it is not one."""
    blob = bytes(blob)
    if len(blob) < _HEADER.size or blob[:4] != MAGIC:
        raise CodecError(f"{source}: not a compact submap (expected {_HEADER.size}+ bytes starting with "
                         f"{MAGIC!r}, got {len(blob)} bytes starting with {blob[:4]!r})")
    head = _HEADER.unpack_from(blob)
    version, codec, bits = head[1], head[2], head[4:9]
    if version not in _READS:
        raise CodecError(f"{source}: compact submap format version {version}, this version reads "
                         f"{' and '.join(map(str, _READS))}")
    exact = all(b == 32 for b in bits)
    link = version == LINK_VERSION
    if codec not in _CODECS.values() or not (exact or all(b in (8, 16) for b in bits[1:])) or \
            not (exact or bits[0] in (range(MIN_MEAN_BITS, 17) if link else (16,))) or \
            (link and (exact or codec != _CODECS["lzma"])):
        raise CodecError(f"{source}: unknown codec {codec} or bits {list(bits)} for format version {version} "
                         f"(expected codec 0-2, means 16 bits, the rest 8/16, or all 32; the link form: lzma, "
                         f"means {MIN_MEAN_BITS}-16 bits)")
    length, crc = head[17:19]
    body = blob[_HEADER.size:]
    if len(body) != length or zlib.crc32(body) != crc:
        raise CodecError(f"{source}: corrupt compact submap (expected a {length}-byte payload with CRC-32 "
                         f"{crc:08x}, got {len(body)} bytes with CRC-32 {zlib.crc32(body):08x})")
    try:
        if version == LINK_VERSION:
            if len(body) < _LENGTHS.size or _LENGTHS.size + sum(_LENGTHS.unpack_from(body)) != len(body):
                raise CodecError(f"{source}: link-form payload lengths do not add up to its {len(body)} bytes")
            at, parts = _LENGTHS.size, []
            for k in _LENGTHS.unpack_from(body):
                parts.append(lzma.decompress(body[at:at + k]))
                at += k
            raw = b"".join(parts)
        else:
            raw = {0: lambda d: d, 1: zlib.decompress, 2: lzma.decompress}[codec](body)
    except (zlib.error, lzma.LZMAError) as e:
        raise CodecError(f"{source}: corrupt compact submap payload ({e})") from None
    n = head[3]
    want = sum(n * _WIDTH[name] * _container(b) for name, b in zip(_QUANTITIES, bits))
    if len(raw) != want:
        raise CodecError(f"{source}: payload of {len(raw)} bytes, expected {want} for {n} Gaussians")
    return head, raw


def _quantised(head: tuple, raw: bytes) -> dict[str, np.ndarray]:
    """The quantised arrays [N, k] (uint16 or uint8) of a stored-form payload, or of a link-form payload with its
    means' delta coding undone."""
    n, bits, out, at = head[3], head[4:9], {}, 0
    for name, b in zip(_QUANTITIES, bits):
        k = n * _WIDTH[name]
        if b == 8:
            q = np.frombuffer(raw, np.uint8, k, at)
        else:
            hi = np.frombuffer(raw, np.uint8, k, at).astype(np.uint16)
            q = (hi << 8) | np.frombuffer(raw, np.uint8, k, at + k)
        at += k * _container(b)
        if head[1] == LINK_VERSION:  # planes per component
            q = q.reshape(_WIDTH[name], n).T
            if name == "means":
                q = _undelta(q)
        out[name] = np.ascontiguousarray(q.reshape(n, _WIDTH[name]))
    return out


def decode(blob: bytes, *, source: str = "compact submap") -> GaussianParams:
    """GaussianParams (float32, CPU) from the bytes of `encode` (the stored form) or `for_link` (the link form:
    the same values, in the Morton order); CodecError naming `source` and what was expected when the bytes are not
    such a blob."""
    head, raw = _parse(blob, source)
    n, bits, box = head[3], head[4:9], head[9:17]
    t = lambda a: torch.from_numpy(np.array(a, dtype=np.float32, order="C"))  # noqa: E731
    if all(b == 32 for b in bits):
        a = np.frombuffer(raw, np.float32)
        cut = np.cumsum([0] + [n * _WIDTH[name] for name in _QUANTITIES])
        m, s, q, o, c = (a[i:j].reshape(n, _WIDTH[name]) for i, j, name in zip(cut[:-1], cut[1:], _QUANTITIES))
        return GaussianParams(t(m), t(s), t(q), t(o[:, 0]), t(c))
    lo_m, hi_m, lo_s, hi_s = np.array(box[0:3]), np.array(box[3:6]), box[6], box[7]
    out, qs = {}, _quantised(head, raw)
    for name, b in zip(_QUANTITIES, bits):
        lo, span = _affine(name, lo_m, hi_m, lo_s, hi_s)
        out[name] = lo + qs[name].astype(np.float64) / _steps(b) * span
    half = 0.5 / _steps(bits[3])  # opacities 0 and 1 have no finite logit: stay within half a step of them
    o = np.clip(out["opacities"][:, 0], half, 1.0 - half)
    return GaussianParams(t(out["means"]), t(out["log_scales"]), t(out["quats"]), t(np.log(o / (1.0 - o))),
                          t(out["colors"]))


def _morton(q: np.ndarray) -> np.ndarray:
    """[N] uint64 Z-order codes of 16-bit coordinates q [N, 3] (the bits of x, y, z interleaved)."""
    code = np.zeros(len(q), np.uint64)
    for bit in range(16):
        for axis in range(3):
            code |= ((q[:, axis].astype(np.uint64) >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


def _delta(q: np.ndarray) -> np.ndarray:
    """uint16 [N, k] -> each column's differences from the row before (16-bit wrap), zigzag-coded: small steps
    in either direction become small numbers."""
    d = np.diff(q.astype(np.int64), axis=0, prepend=0)
    d = (d + 32768) % 65536 - 32768
    return np.where(d >= 0, 2 * d, -2 * d - 1).astype(np.uint16)


def _undelta(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.int64)
    d = np.where(z & 1, -(z >> 1) - 1, z >> 1)
    return (np.cumsum(d, axis=0) % 65536).astype(np.uint16)


def for_link(blob: bytes, keep: np.ndarray | None = None, *, mean_bits: int = 16,
             source: str = "compact submap") -> bytes:
    """The link form (module docstring) of a stored-form blob's Gaussians, the ones where `keep` [N] bool is true
    (None: all), in the Morton order of their means. With mean_bits 16 they decode to exactly the values the
    stored form decodes to (the box and log-scale range stay the stored form's); with fewer, the means are
    quantised again to that many bits within the same box (each within half a step of either grid of the stored
    mean: `error_bounds` with those bits, plus the stored form's own half step). CodecError for bytes that are
    not a quantised stored form (an exact, float32 one: encode its parameters with `encode` first)."""
    if not MIN_MEAN_BITS <= mean_bits <= 16:
        raise InputError(f"for_link: mean_bits must be {MIN_MEAN_BITS}-16, got {mean_bits}")
    head, raw = _parse(blob, source)
    if head[1] != VERSION or all(b == 32 for b in head[4:9]):
        raise CodecError(f"{source}: the link form is made from a quantised stored form (version {VERSION}), got "
                         f"version {head[1]} with bits {list(head[4:9])}")
    q = _quantised(head, raw)
    n = head[3]
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (n,):
            raise InputError(f"for_link: keep must be [{n}] bool, got {list(keep.shape)}")
        q = {k: v[keep] for k, v in q.items()}
        n = int(keep.sum())
    if mean_bits < 16:
        q["means"] = np.rint(q["means"].astype(np.float64) * (_steps(mean_bits) / _steps(16))).astype(np.uint16)
    order = np.argsort(_morton(q["means"]), kind="stable")
    parts = []
    for name in _QUANTITIES:
        v = q[name][order]
        parts.append(_planes((_delta(v) if name == "means" else v).T.copy()))
    streams = [lzma.compress(p, preset=6) for p in parts]
    body = _LENGTHS.pack(*map(len, streams)) + b"".join(streams)
    return _HEADER.pack(MAGIC, LINK_VERSION, _CODECS["lzma"], n, mean_bits, *head[5:9], *head[9:17], len(body),
                        zlib.crc32(body)) + body


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
