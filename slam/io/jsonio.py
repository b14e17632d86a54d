"""metrics.json and friends: strict JSON (no NaN/Inf, no NumPy scalars), written atomically."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from swarmsplat.kernels.fileio import atomic_write_text


def finite_json(x):
    """A copy of `x` that strict JSON can hold: NaN/Inf become null, NumPy scalars become Python numbers."""
    if isinstance(x, dict):
        return {k: finite_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_json(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.integer, np.bool_)):
        return x.item()
    return x


def write_json(path: str | Path, data) -> Path:
    """Write `data` as indented strict JSON, atomically."""
    return atomic_write_text(path, json.dumps(finite_json(data), indent=2, allow_nan=False))
