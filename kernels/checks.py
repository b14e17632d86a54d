"""Boundary checks for tensors entering a kernel: shape, dtype, device, finiteness — once, with a clear error."""

from __future__ import annotations

from typing import Sequence

import torch

from .errors import InputError


def check_tensor(
    name: str,
    x,
    shape: Sequence[int | None],
    *,
    dtypes: Sequence[torch.dtype] = (torch.float32, torch.float64),
    device: str | torch.device | None = None,
    finite: bool = True,
) -> torch.Tensor:
    """Validate one argument. `shape` uses None for a free dimension, e.g. (None, 3) for [N, 3].

    Raises InputError naming the argument and what was expected.
    """
    if not isinstance(x, torch.Tensor):
        raise InputError(f"argument '{name}': expected a torch.Tensor, got {type(x).__name__}")
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise InputError(f"argument '{name}': expected shape {want}, got {list(x.shape)}")
    if dtypes and x.dtype not in dtypes:
        raise InputError(f"argument '{name}': expected dtype {' or '.join(str(d) for d in dtypes)}, got {x.dtype}")
    if device is not None and torch.device(device).type != x.device.type:
        raise InputError(f"argument '{name}': expected a tensor on {torch.device(device).type}, got one on {x.device.type}")
    if finite and x.is_floating_point() and x.numel() and not bool(torch.isfinite(x).all()):
        raise InputError(f"argument '{name}': contains NaN or Inf")
    return x
