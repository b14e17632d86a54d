"""The twins: obvious NumPy / plain-torch versions of every kernel (float64 where it matters).

They are the specification the Warp and Taichi kernels are tested against, never the production path. Each
kernel family keeps its twin in its own file (`_ref_raster.py`, `_ref_icp.py`); this module is the one place
tests and users import them from.
"""

from __future__ import annotations

import importlib

_PARTS = ("_ref_raster", "_ref_icp")


def __getattr__(name: str):
    for part in _PARTS:
        try:
            mod = importlib.import_module(f"{__package__}.{part}")
        except ModuleNotFoundError as e:
            if e.name == f"{__package__}.{part}":
                continue
            raise
        if hasattr(mod, name):
            return getattr(mod, name)
    raise AttributeError(f"kernels.reference has no twin named {name!r}")
