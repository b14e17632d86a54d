"""torch tensor -> Warp array views for kernel launches, cached by (address, shape, strides, dtype, device).

`wp.from_torch` costs tens of microseconds per array, and a rasteriser call passes ~70 arrays; the per-call
buffers are fresh tensors, but torch's allocator hands the same addresses back call after call, so a view built
once for an address and layout is reused. A cached view does not own or keep its memory alive: it is only valid
while the caller holds the tensor, i.e. for the launch it is made for (every view is re-looked-up per launch).
"""

from __future__ import annotations

import torch
import warp as wp

_TYPES = {torch.float32: wp.float32, torch.int32: wp.int32}
_CACHE: dict = {}
_CACHE_MAX = 4096


def to_warp(t: torch.Tensor, dtype=None):
    """A Warp array viewing `t` (float32 or int32, any strides, 0 included); detached, no Warp-side gradient."""
    # the key's parts are the cheap tensor attributes (~1 us in all; t.device.type alone costs ~1 us)
    key = (t.data_ptr(), t.shape, t.stride(), t.dtype, t.is_cuda)
    a = _CACHE.get(key)
    if a is None:
        if len(_CACHE) >= _CACHE_MAX:
            _CACHE.clear()
        if t.dtype not in _TYPES or dtype is not None or not t.is_cpu or t.numel() == 0:
            return wp.from_torch(t.detach(), dtype=dtype, requires_grad=False)
        size = t.element_size()
        a = wp.array(ptr=t.data_ptr(), dtype=_TYPES[t.dtype], shape=tuple(t.shape),
                     strides=tuple(s * size for s in t.stride()), device="cpu")
        a.__ctype__()  # the descriptor kernels/_warp/launch.py `run` passes (a.ctype from now on)
        _CACHE[key] = a
    return a
