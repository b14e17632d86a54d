"""torch tensor -> Warp kernel argument.

On the CPU a float32 / int32 tensor becomes a `Flat`: the twelve values of Warp's bare array descriptor (`array_t`:
data pointer, grad pointer, shape[4], byte strides[4], ndim, flags) as a tuple. kernels/_warp/launch.py `run` packs
a launch's Flats and scalars into the kernel's argument struct with one struct.pack (~12 us for a 16-array
launch; building a ctypes descriptor per array and then the struct from them took ~20 us), and turns them into
`array_t`s for wp.launch. A Flat is built fresh per launch: a wp.array costs ~24 us to create, and a cache of them
by (address, layout) missed ~7 of a rasteriser call's ~75 arrays (torch's allocator does not hand every address
back in the same order), while its growing population of long-lived objects made Python's full garbage
collections (~0.2 s each) come round. A Flat does not own or keep its memory alive: it is only valid while the
caller holds the tensor, i.e. for the launch it is made for. CUDA tensors and other dtypes go through
wp.from_torch.
"""

from __future__ import annotations

import ctypes
import struct

import torch
import warp as wp

_TYPES = (torch.float32, torch.int32)
LAYOUT = struct.Struct("<QQ4i4iHH4x")  # array_t: data, grad, shape[4], strides[4] (bytes), ndim, flags, padding
try:  # the descriptor type Warp's launches pass (Warp 1.19's layout); another Warp: wp.from_torch for everything
    from warp._src.types import array_t

    _from = array_t.from_buffer_copy if LAYOUT.size == ctypes.sizeof(array_t) else None
except ImportError:
    _from = None


class Flat(tuple):
    """The twelve values of an `array_t` in LAYOUT's order (see the module docstring)."""

    __slots__ = ()


def as_array_t(f: Flat):
    """The ctypes `array_t` of a Flat (what wp.launch takes)."""
    return _from(LAYOUT.pack(*f))


def to_warp(t: torch.Tensor, dtype=None):
    """A Warp kernel argument viewing `t` (float32 or int32, up to 4 dims, any strides, 0 included); detached, no
    Warp-side gradient."""
    if _from is not None and dtype is None and t.is_cpu and t.dtype in _TYPES:
        sh, st = t.shape, t.stride()
        nd = len(sh)
        if nd == 1:
            return Flat((t.data_ptr(), 0, sh[0], 0, 0, 0, 4 * st[0], 0, 0, 0, 1, 0))
        if nd == 2:
            return Flat((t.data_ptr(), 0, sh[0], sh[1], 0, 0, 4 * st[0], 4 * st[1], 0, 0, 2, 0))
        if 0 < nd <= 4:
            shape = tuple(sh) + (0,) * (4 - nd)
            strides = tuple(4 * s for s in st) + (0,) * (4 - nd)
            return Flat((t.data_ptr(), 0, *shape, *strides, nd, 0))
    return wp.from_torch(t.detach(), dtype=dtype, requires_grad=False)


def to_warp_1d(t: torch.Tensor):
    """to_warp of `t` flattened, for a contiguous `t` or a broadcast one (every stride 0: one value read for all),
    without making the torch view (~1 us each). Other layouts: ValueError (make them contiguous first)."""
    broadcast = all(st == 0 for st in t.stride())
    if not (broadcast or t.is_contiguous()):
        raise ValueError(f"to_warp_1d: expected a contiguous or broadcast tensor, got strides {t.stride()}")
    if _from is not None and t.is_cpu and t.dtype in _TYPES:
        return Flat((t.data_ptr(), 0, t.numel(), 0, 0, 0, 0 if broadcast else 4, 0, 0, 0, 1, 0))
    return to_warp(t.as_strided((t.numel(),), (0,)) if broadcast else t.view(-1))


def to_warp_rows(t: torch.Tensor) -> list:
    """[to_warp(t[k]) for each k along the first dim] of a 2- to 4-D tensor, without making the torch views for a
    contiguous one."""
    if _from is not None and t.is_cpu and t.dtype in _TYPES and t.is_contiguous():
        p, sh = t.data_ptr(), t.shape
        if len(sh) == 2:
            step = 4 * sh[1]
            return [Flat((p + step * k, 0, sh[1], 0, 0, 0, 4, 0, 0, 0, 1, 0)) for k in range(sh[0])]
        if len(sh) == 3:
            step = 4 * sh[1] * sh[2]
            return [Flat((p + step * k, 0, sh[1], sh[2], 0, 0, 4 * sh[2], 4, 0, 0, 2, 0)) for k in range(sh[0])]
    return [to_warp(r) for r in t]
