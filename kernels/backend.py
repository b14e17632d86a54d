"""Run-time choice of kernel backend (Warp or Taichi) and device (cpu, cuda or vulkan).

Nothing here runs at import time: `use()` initialises the chosen backend on first call, and the kernel modules
ask `active()` for the choice when they launch. Warp and Taichi both compile the same kernel source for the CPU
(LLVM) and for CUDA, so one string picks the device for every kernel. Taichi also generates SPIR-V for Vulkan
(any Vulkan 1.x GPU, or Mesa's software driver lavapipe); on Vulkan the tensors stay torch CPU tensors and Taichi
copies them to the device and back around each launch. Warp has no Vulkan backend. docs/gpu.md has the details.
"""

from __future__ import annotations

import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass

from .errors import BackendError

BACKENDS = ("warp", "taichi")
DEVICES = ("cpu", "cuda", "vulkan")
# Which backend compiles for which device (Warp: LLVM CPU + CUDA; Taichi: LLVM CPU + CUDA + SPIR-V Vulkan).
SUPPORTED = {"warp": ("cpu", "cuda"), "taichi": ("cpu", "cuda", "vulkan")}


@dataclass(frozen=True)
class Backend:
    name: str  # "warp" | "taichi"
    device: str  # "cpu" | "cuda" | "vulkan"

    @property
    def torch_device(self) -> str:
        """Where the kernels' torch tensors live: cuda for CUDA, else the CPU (Vulkan copies per launch)."""
        return "cuda" if self.device == "cuda" else "cpu"


_lock = threading.Lock()
_active: Backend | None = None
_reference = False  # inside `use_reference()`: kernels with a twin run the twin
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
        # Warp's native library tells stderr when it finds no CUDA driver, on every CPU-only machine; on the CPU that
        # is no news (asking for cuda without one is a BackendError below), so the probe runs with fd 2 quiet.
        (wp.init if device == "cuda" else lambda: _quiet_fd2(wp.init))()
        _warp_ready = True
    if device == "cuda" and not wp.is_cuda_available():
        raise BackendError("device 'cuda' was asked for, but Warp finds no CUDA device on this machine; use --device cpu")


def _quiet_fd2(fn):
    """fn() with the process's stderr (fd 2) sent to /dev/null: Taichi's C++ driver probes print "RHI Error"
    lines for a missing Vulkan driver, which is an answer here, not an error. (Process-wide for the ~0.1 s of
    the probe: another thread's stderr in that window is lost too.)"""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            return fn()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _taichi_has(device: str) -> bool:
    """True when Taichi's runtime for `device` loads here: for vulkan a Vulkan instance is created with the
    installed loader and drivers; for cuda the CUDA driver library loads. No ti.init, nothing changes."""
    import taichi as ti

    if device == "cpu":
        return True
    probe = ti._lib.core.with_vulkan if device == "vulkan" else ti._lib.core.with_cuda
    try:
        return bool(_quiet_fd2(probe))
    except Exception:  # noqa: BLE001 - any failure to probe means "not available"
        return False


def _ti_init(device: str) -> bool:
    """ti.init on `device`; False (and Taichi reset) when Taichi fell back to another arch."""
    import taichi as ti

    arch = {"cpu": ti.cpu, "cuda": ti.cuda, "vulkan": ti.vulkan}[device]
    kwargs = dict(arch=arch, default_fp=ti.f32, log_level=ti.ERROR, offline_cache=True)
    if device == "cpu":
        kwargs["cpu_max_num_threads"] = max(1, os.cpu_count() or 1)
    ti.init(**kwargs)
    # ti.init silently falls back to the CPU when the GPU arch is missing; a user who asked for a GPU must know.
    if ti.lang.impl.current_cfg().arch != arch:
        ti.reset()
        return False
    return True


def _init_taichi(device: str) -> None:
    global _taichi_arch
    import taichi as ti

    if _taichi_arch == device:
        return
    ok = _taichi_has(device)
    if ok:
        if _taichi_arch is not None:
            ti.reset()  # Taichi holds one arch per process
            _taichi_arch = None
        ok = _ti_init(device)
        if not ok and _active is not None and _active.name == "taichi" and _ti_init(_active.device):
            _taichi_arch = _active.device  # the choice in force before this call keeps working
    if not ok:
        what = "CUDA device" if device == "cuda" else "Vulkan driver (install mesa-vulkan-drivers and libvulkan1)"
        raise BackendError(f"device {device!r} was asked for, but Taichi finds no {what} on this machine; "
                           "use --device cpu")
    _taichi_arch = device


def use(backend: str = "warp", device: str = "cpu") -> Backend:
    """Select the kernel backend and device for every kernel launched after this call.

    backend: "warp" or "taichi"; device: "cpu", "cuda" or "vulkan" (Taichi only). Raises BackendError (one clear
    line) for an unknown name, a pair that does not exist (warp + vulkan) or a device that this machine does not
    have. Safe to call again to switch.
    """
    global _active
    backend = str(backend).lower()
    device = str(device).lower()
    if backend not in BACKENDS:
        raise BackendError(f"unknown kernel backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if device not in DEVICES:
        raise BackendError(f"unknown device {device!r}; expected one of {', '.join(DEVICES)}")
    if device not in SUPPORTED[backend]:
        raise BackendError(f"kernel backend {backend!r} has no {device!r} device (it runs on "
                           f"{' or '.join(SUPPORTED[backend])}); use --kernels taichi --device {device}")
    if device == "cuda" and not _cuda_for_torch():
        raise BackendError("device 'cuda' was asked for, but torch sees no CUDA device on this machine; use --device cpu")
    with _lock:
        if backend == "warp":
            _init_warp(device)
        else:
            _init_taichi(device)
        _active = Backend(backend, device)
        return _active


@contextmanager
def use_reference(on: bool = True):
    """Inside the block, the kernels that have a twin in `kernels.reference` (the rasteriser, the parameter
    activations) run the twin: plain torch, slow, the specification the backends are tested against. Everything
    else keeps running on the backend chosen with `use()`. Process-wide while the block runs; nests, and the
    previous choice returns on leaving it. on=False runs the backend inside an outer block."""
    global _reference
    before = _reference
    _reference = bool(on)
    try:
        yield
    finally:
        _reference = before


def reference_active() -> bool:
    """True inside `use_reference()`: callers with a twin run it instead of the backend's kernel."""
    return _reference


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


def devices(run: bool = False) -> list[Backend]:
    """The backend/device pairs that work on this machine, in the order warp-cpu, warp-cuda, taichi-cpu,
    taichi-cuda, taichi-vulkan.

    run=False (cheap, nothing changes): each pair's runtime loads — the CPU always; CUDA when torch sees a CUDA
    device and Warp / Taichi load the CUDA driver; Vulkan when Taichi creates a Vulkan instance with the installed
    loader and drivers. run=True: additionally selects each pair and runs the axpy probe kernel and the device
    self-check on it (kernels.selfcheck: a 320x240 probe render, forward and backward, against the twin), then
    selects the pair that was active before again (Taichi re-initialises when its arch changes).
    """
    found = []
    for name in BACKENDS:
        for device in SUPPORTED[name]:
            if device == "cuda" and not cuda_available():
                continue
            try:
                if name == "warp":
                    with _lock:
                        _init_warp(device)
                elif not _taichi_has(device):
                    continue
            except (ImportError, BackendError):
                continue
            found.append(Backend(name, device))
    if not run:
        return found
    return [b for b in found if _runs(b)]


def _runs(b: Backend) -> bool:
    """Select `b`, run y <- 2 x + y on it and compare, then the self-check's probe render; the previously active
    pair is selected again after."""
    global _active
    import torch

    from . import axpy

    before = _active
    try:
        use(b.name, b.device)
        x = torch.arange(64, dtype=torch.float32, device=b.torch_device)
        y = torch.ones(64, dtype=torch.float32, device=b.torch_device)
        axpy(2.0, x, y)
        if not torch.equal(y.cpu(), 2.0 * torch.arange(64, dtype=torch.float32) + 1.0):
            return False
        from .selfcheck import self_check

        return self_check(b.name, b.device).ok
    except BackendError:
        return False
    finally:
        if before is not None:
            use(before.name, before.device)
        else:
            _active = None
