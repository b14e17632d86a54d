"""Save and load Gaussian maps as the standard 3DGS PLY that common splat viewers open.

Binary little-endian vertex element with float32 properties, in this order:
  x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3
with opacity as a logit, scales as logs, rot as a wxyz quaternion and colour as the degree-0 spherical-harmonic
coefficient f_dc = (rgb - 0.5) / C0, C0 = 0.28209479 (what 3DGS writes). Extra properties (e.g. f_rest_*) in a
file are ignored on load. Normals are written as zeros, as 3DGS does.
"""

from __future__ import annotations

import os

from pathlib import Path

import numpy as np
import torch

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path

from .gaussian_map import GaussianParams

SH_C0 = 0.28209479177387814

_PROPS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
          + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "ushort": "u2", "uint16": "u2", "short": "i2", "int16": "i2",
              "uint": "u4", "uint32": "u4", "int": "i4", "int32": "i4"}


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(f_dc: np.ndarray) -> np.ndarray:
    return f_dc * SH_C0 + 0.5


def save_ply(path: str | Path, params: GaussianParams, *, max_color: float | None = 1.0) -> Path:
    """Write `params` (any frame; usually the merged world map) as a 3DGS PLY, atomically. Colours are clamped to
    [0, max_color]: 1 as the rasteriser clamps each Gaussian's colour; None keeps colours above 1 (a map brought
    to a keyframe's exposure for display, slam.dense.mapping.exposure.for_display: a 3DGS viewer clamps the
    composited pixel)."""
    n = len(params)
    with torch.no_grad():
        cols = [
            params.means.double(),
            torch.zeros(n, 3, dtype=torch.float64),
            torch.as_tensor(rgb_to_sh_dc(params.colors.detach().double().clamp(0, max_color).cpu().numpy())),
            params.logit_opacities.detach().double()[:, None],
            params.log_scales.detach().double(),
            params.quats.detach().double(),
        ]
        data = torch.cat([c.cpu() for c in cols], dim=1).numpy().astype("<f4")
    if not np.all(np.isfinite(data)):
        raise InputError(f"save_ply({path}): the map contains NaN or Inf parameters")
    header = "ply\nformat binary_little_endian 1.0\n"
    header += "comment swarmsplat 3DGS map (logit opacity, log scales, wxyz rot, SH DC colour)\n"
    header += f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in _PROPS) + "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
    return Path(path)


def _parse_header(path: Path, f) -> tuple[str, int, list[tuple[str, str]]]:
    first = f.readline()
    if first.strip() != b"ply":
        raise InputError(f"{path}:1: not a PLY file (expected 'ply', got {first[:20]!r})")
    fmt, count, props, in_vertex, lineno = None, None, [], False, 1
    while True:
        raw = f.readline()
        lineno += 1
        if not raw:
            raise InputError(f"{path}: PLY header has no 'end_header'")
        parts = raw.decode("ascii", errors="replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif parts[0] == "element":
            in_vertex = len(parts) == 3 and parts[1] == "vertex"
            if in_vertex:
                try:
                    count = int(parts[2])
                except ValueError:
                    count = -1
                if count < 0:
                    raise InputError(f"{path}:{lineno}: bad vertex count {parts[2]!r} (expected a whole number >= 0)")
            elif count is not None:
                # Elements after the vertices (faces) would follow the vertex data; we read only vertices.
                pass
        elif parts[0] == "property" and in_vertex:
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise InputError(f"{path}:{lineno}: unsupported vertex property line {' '.join(parts)!r}")
            if any(parts[2] == q for q, _ in props):
                raise InputError(f"{path}:{lineno}: vertex property {parts[2]!r} declared twice")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("binary_little_endian", "ascii"):
        raise InputError(f"{path}: PLY format {fmt!r} not supported (expected binary_little_endian or ascii)")
    if count is None:
        raise InputError(f"{path}: PLY has no 'element vertex N'")
    return fmt, count, props


def load_ply(path: str | Path, device: str | torch.device = "cpu") -> GaussianParams:
    """Read a 3DGS PLY written by us or by 3DGS-style trainers. Raises InputError for a malformed file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        fmt, count, props = _parse_header(path, f)
        names = [p for p, _ in props]
        missing = [p for p in _PROPS if p not in names and not p.startswith("n")]
        if missing:
            raise InputError(f"{path}: not a 3DGS PLY, missing vertex properties {', '.join(missing)}")
        dtype = np.dtype([(p, "<" + t) for p, t in props])
        if fmt == "ascii":
            try:
                arr = np.loadtxt(f, max_rows=count, ndmin=2)
            except ValueError as e:
                raise InputError(f"{path}: bad ASCII PLY data ({e})") from None
            if arr.shape != (count, len(props)):
                raise InputError(f"{path}: expected {count} rows of {len(props)} values, got {list(arr.shape)}")
            rec = {p: arr[:, i] for i, p in enumerate(names)}
        else:
            need, left = count * dtype.itemsize, os.fstat(f.fileno()).st_size - f.tell()
            if need > left:  # before reading: a count past any file's size is not an allocation to try
                raise InputError(f"{path}: truncated PLY: {count} vertices need {need} bytes, found {left}")
            buf = f.read(need)
            a = np.frombuffer(buf, dtype=dtype, count=count)
            rec = {p: a[p] for p in names}
    col = lambda *ps: np.stack([np.asarray(rec[p], dtype=np.float64) for p in ps], axis=1)  # noqa: E731
    means = col("x", "y", "z")
    rgb = sh_dc_to_rgb(col("f_dc_0", "f_dc_1", "f_dc_2"))
    opac = np.asarray(rec["opacity"], dtype=np.float64)
    scales = col("scale_0", "scale_1", "scale_2")
    rots = col("rot_0", "rot_1", "rot_2", "rot_3")
    for name, a in (("position", means), ("colour", rgb), ("opacity", opac), ("scale", scales), ("rotation", rots)):
        if not np.all(np.isfinite(a)):
            raise InputError(f"{path}: NaN or Inf in Gaussian {name}s")
    if count and np.any(np.linalg.norm(rots, axis=1) < 1e-12):
        raise InputError(f"{path}: a Gaussian has a zero-length rotation quaternion")
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)  # noqa: E731
    return GaussianParams(t(means), t(scales), t(rots), t(opac), t(rgb))
