"""swarmsplat's numeric core: Warp and Taichi kernels behind one typed API, their NumPy/torch twins
(`kernels.reference`), and the geometry every layer shares (SE(3), cameras).

Choose the backend and device once, at run time: `kernels.use(backend="warp"|"taichi", device="cpu"|"cuda"|
"vulkan")` (vulkan: Taichi only); `kernels.devices()` lists the pairs that work on this machine. Inside
`with kernels.use_reference():` the kernels that have a twin run it instead (tests, checks). Nothing
initialises Warp or Taichi at import time; backend modules load on first use. GPU notes: docs/gpu.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from . import se3, selfcheck
from .backend import Backend, active, cuda_available, devices, reference_active, use, use_reference
from .camera import PinholeCamera
from .errors import (BackendError, DeviceCheckError, GraphError, InputError, RegistrationError, SanityError,
                     SwarmsplatError)

__all__ = [
    "use", "use_reference", "reference_active", "active", "devices", "cuda_available", "Backend", "backend_module",
    "PinholeCamera", "se3", "selfcheck", "check_tensor", "axpy",
    "SwarmsplatError", "InputError", "BackendError", "DeviceCheckError", "RegistrationError", "GraphError",
    "SanityError",
]


# Public names that live in their own modules, imported on first access (keeps `import kernels` light and
# lets each kernel family own its file). name -> module under kernels/. The module names differ from the
# function names on purpose: importing a submodule sets it as a package attribute and would shadow the function.
_LAZY = {
    "rasterize": "raster",
    "RenderOutput": "raster",
    "check_tensor": "checks",  # imports torch: not loaded by `import swarmsplat.kernels` (graph/ runs without it)
}

if TYPE_CHECKING:
    import torch


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'kernels' has no attribute {name!r}")


def backend_module(name: str):
    """The active backend's implementation module `kernels._<backend>.<name>` (imported lazily)."""
    b = active()
    return importlib.import_module(f"{__name__}._{b.name}.{name}")


def axpy(a: float, x: "torch.Tensor", y: "torch.Tensor") -> "torch.Tensor":
    """y <- a * x + y in place on the active backend; the probe that proves the backend plumbing works.

    x, y: float32 [N] on the active device.
    """
    import torch

    from .checks import check_tensor

    b = active()
    check_tensor("x", x, (None,), dtypes=(torch.float32,), device=b.torch_device)
    check_tensor("y", y, (x.shape[0],), dtypes=(torch.float32,), device=b.torch_device)
    if not (x.is_contiguous() and y.is_contiguous()):
        raise InputError("arguments 'x' and 'y' must be contiguous")
    return backend_module("axpy").axpy(a, x, y, b.device)
