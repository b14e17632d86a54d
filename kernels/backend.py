"""Run-time choice of kernel backend (Warp or Taichi) and device (cpu or cuda).

Nothing here runs at import time: `use()` initialises the chosen backend on first call, and the kernel modules
ask `active()` for the choice when they launch. Warp and Taichi both compile the same kernel source for the CPU
(LLVM) and for CUDA, so one string picks the device for every kernel.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

from .errors import BackendError

BACKENDS = ("warp", "taichi")
DEVICES = ("cpu", "cuda")


@dataclass(frozen=True)
class Backend:
    name: str  # "warp" | "taichi"
    device: str  # "cpu" | "cuda"

    @property
    def torch_device(self) -> str:
        return "cuda" if self.device == "cuda" else "cpu"


_lock = threading.Lock()
_active: Backend | None = None
_taichi_arch: str | None = None  # Taichi can only hold one arch per process at a time
_warp_ready = False


def _cuda_for_torch() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def _init_warp(device: str) -> None:
    global _warp_ready
    import warp as wp

    if not _warp_ready:
        # Keep start-up banners and per-module compile timings off the user's terminal.
        wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
        wp.init()
        _warp_ready = True
    if device == "cuda" and not wp.is_cuda_available():
        raise BackendError("device 'cuda' was asked for, but Warp finds no CUDA device on this machine; use --device cpu")


def _init_taichi(device: str) -> None:
    global _taichi_arch
    import taichi as ti

    if _taichi_arch == device:
        return
    if _taichi_arch is not None:
        ti.reset()
    arch = ti.cuda if device == "cuda" else ti.cpu
    kwargs = dict(arch=arch, default_fp=ti.f32, log_level=ti.ERROR, offline_cache=True)
    if device == "cpu":
        kwargs["cpu_max_num_threads"] = max(1, os.cpu_count() or 1)
    ti.init(**kwargs)
    # ti.init silently falls back to the CPU when CUDA is missing; a user who asked for cuda must know.
    if device == "cuda" and ti.lang.impl.current_cfg().arch != ti.cuda:
        ti.reset()
        _taichi_arch = None
        raise BackendError("device 'cuda' was asked for, but Taichi finds no CUDA device on this machine; use --device cpu")
    _taichi_arch = device


def use(backend: str = "warp", device: str = "cpu") -> Backend:
    """Select the kernel backend and device for every kernel launched after this call.

    backend: "warp" or "taichi"; device: "cpu" or "cuda". Raises BackendError (one clear line) for an unknown
    name or a device that this machine does not have. Safe to call again to switch.
    """
    global _active
    backend = str(backend).lower()
    device = str(device).lower()
    if backend not in BACKENDS:
        raise BackendError(f"unknown kernel backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if device not in DEVICES:
        raise BackendError(f"unknown device {device!r}; expected one of {', '.join(DEVICES)}")
    if device == "cuda" and not _cuda_for_torch():
        raise BackendError("device 'cuda' was asked for, but torch sees no CUDA device on this machine; use --device cpu")
    with _lock:
        if backend == "warp":
            _init_warp(device)
        else:
            _init_taichi(device)
        _active = Backend(backend, device)
        return _active


def active() -> Backend:
    """The backend chosen by `use()`; selects Warp on the CPU when nothing was chosen yet."""
    if _active is None:
        return use("warp", "cpu")
    return _active


def cuda_available() -> bool:
    """True when a CUDA device is visible to torch (tests use it to skip CUDA cases)."""
    try:
        return _cuda_for_torch()
    except Exception:  # noqa: BLE001 - any failure to probe means "not available"
        return False
