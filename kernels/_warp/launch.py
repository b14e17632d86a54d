"""Warp CPU launches split over the cores: Warp's CPU backend runs one launch on one thread, and its ctypes call
releases the GIL, so a launch over many items is cut into one contiguous part per core, each launched from its own
Python thread (the ICP kernels use it; results are bitwise equal to one launch, tests/test_icp_threads.py)."""

from __future__ import annotations

import ctypes
import math
import os
import struct as _struct
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from .arrays import LAYOUT, Flat, as_array_t

_POOLS: dict = {}  # nice value -> (pool, pid)
_POOL_LOCK = threading.Lock()
_LOADED: set = set()  # (kernel, device) launched at least once: compiled and loaded, safe to launch from threads
_PER_THREAD_NICE = sys.platform.startswith("linux")  # Linux keeps a nice value per thread


def _cpu_threads() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _nice() -> int:
    """The calling thread's nice value (0 where threads have none of their own)."""
    if not _PER_THREAD_NICE:
        return 0
    try:
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    except OSError:
        return 0


def _set_nice(nice: int) -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except OSError:
        pass  # raising a priority needs a privilege: keep what the thread has


def _pool(workers: int) -> ThreadPoolExecutor:
    """The pool that runs the calling thread's parts: one per process and nice value, its threads at that nice
    value. A thread that lowered its priority (slam/run/realtime's mapping worker) so never queues its parts in
    front of a normal thread's (the tracker's), and its parts run at its own priority."""
    nice = _nice()
    with _POOL_LOCK:
        # a forked child inherits the pool objects but not their threads, so it makes its own
        pool, pid = _POOLS.get(nice, (None, -1))
        if pool is None or pid != os.getpid():
            init = (_set_nice, (nice,)) if _PER_THREAD_NICE else (None, ())
            pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"swarmsplat-warp-cpu-n{nice}",
                                      initializer=init[0], initargs=init[1])
            _POOLS[nice] = (pool, os.getpid())
    return pool


# Direct CPU calls. wp.launch spends ~85 us of Python per launch of a ~20-argument kernel (argument checks and
# packing, module lookup), more than the kernels' own work at small sizes (a 160x120 / 1k-Gaussian rasteriser call
# is 7 launches). After one ordinary launch of a kernel (which compiles and loads its module), `run` calls the
# kernel's CPU entry point itself: the ctypes argument struct laid out as Warp lays it out (the same field types,
# taken from a recorded wp.launch), filled from the array descriptors (kernels/_warp/arrays.py) and the
# scalars, then the forward hook with the launch bounds. Same compiled code, same arguments: the same results.
# Anything unusual (CUDA, a kernel this cannot describe) goes through wp.launch.
_DIRECT: dict = {}  # kernel -> (forward hook, argument struct type, ...) or None (use wp.launch)
_DIRECT_LOCK = threading.Lock()
DIRECT = True  # False: every launch through wp.launch (A/B measurements, tests)
_BOUNDS: dict = {}  # (launch shape, kernel dims) -> Warp's launch-bounds struct (~3 us to build per launch)


def _launchable(inputs: list) -> list:
    """inputs as wp.launch takes them: Flats (kernels/_warp/arrays.py) as Warp's array descriptors."""
    return [as_array_t(a) if type(a) is Flat else a for a in inputs]


def _packer(struct) -> tuple | None:
    """(struct.Struct that packs a launch's flattened Flats and scalars into `struct`'s bytes, which fields are
    arrays), or None where a field is of a type this does not know (the launch then fills the ctypes struct)."""
    try:
        from warp._src.types import array_t
    except ImportError:
        return None
    codes = {ctypes.c_int32: ("i", 4), ctypes.c_float: ("f", 4)}
    fmt, pos, is_array = "<", 0, []
    for name, ty in struct._fields_:
        off = getattr(struct, name).offset
        if ty is array_t and ctypes.sizeof(array_t) == LAYOUT.size:
            code, size = LAYOUT.format.lstrip("<@=!>"), LAYOUT.size
        elif ty in codes:
            code, size = codes[ty]
        else:
            return None
        fmt += f"{off - pos}x{code}" if off > pos else code
        pos = off + size
        is_array.append(ty is array_t)
    tail = ctypes.sizeof(struct) - pos
    packer = _struct.Struct(fmt + (f"{tail}x" if tail else ""))
    return (packer, tuple(is_array)) if packer.size == ctypes.sizeof(struct) else None


def _describe(kernel, dim, inputs: list):
    """(hook, ArgsStruct, kernel_dim, bounds maker, recorded launch, packer) for direct calls of `kernel` on the
    CPU, or None; launches nothing."""
    try:
        from warp._src import context as _ctx  # Warp's own launch machinery (1.19): the layout it passes

        if kernel.is_generic:
            return None
        cmd = wp.launch(kernel, dim=dim, inputs=_launchable(inputs), device="cpu", record_tape=False,
                        record_cmd=True)
        if not isinstance(cmd, _ctx.Launch) or cmd.block_dim > 1 or cmd.hooks.forward is None:
            return None
        fields = [(a.label, type(p)) for a, p in zip(kernel.adj.args, cmd.params[1:])]
        if len(fields) != len(inputs):
            return None
        struct = type("ArgsStruct", (ctypes.Structure,), {"_fields_": fields})
        struct(*cmd.params[1:])  # every field takes its packed value
        # cmd holds the module executable: were the module rebuilt (a kernel added to it later), the loaded
        # code this hook points into stays loaded
        return (cmd.hooks.forward, struct, kernel.adj.kernel_dim, _ctx._build_launch_bounds_from_tuple, cmd,
                _packer(struct))
    except Exception:  # noqa: BLE001 - any surprise: keep wp.launch for this kernel
        return None


def _args(struct, packer, inputs: list):
    """The kernel's argument struct filled from `inputs` (Flats, scalars, Warp arrays)."""
    if packer is not None and len(inputs) == len(packer[1]):
        pack, is_array = packer
        vals: list = []
        for a, arr in zip(inputs, is_array):
            if (type(a) is Flat) is not arr:
                break  # a Warp array (e.g. the ICP's vec3 descriptors), or a misplaced argument: ctypes below
            if arr:
                vals.extend(a)
            else:
                vals.append(a)
        else:
            try:
                return struct.from_buffer_copy(pack.pack(*vals))
            except _struct.error:
                pass  # e.g. a float where an int is expected: ctypes below says so
    return struct(*[as_array_t(a) if type(a) is Flat else a.__ctype__() if isinstance(a, wp.array) else a
                    for a in inputs])


def run(kernel, dim, inputs: list, device: str, gpu_block: int = 256) -> None:
    """wp.launch(kernel, dim, inputs) on `device` (CUDA: `gpu_block` threads per block); on the CPU a direct call
    of the compiled kernel once it has been launched (and so compiled and loaded) once. `inputs` holds array
    descriptors (kernels/_warp/arrays.py), Warp arrays and Python scalars."""
    if device == "cpu" and DIRECT:
        if (dim if isinstance(dim, int) else math.prod(dim)) <= 0:
            return  # wp.launch does nothing either
        d = _DIRECT.get(kernel, False)
        if d:
            hook, struct, kdim, bounds_of, _cmd, packer = d
            args = _args(struct, packer, inputs)
            shape = dim if isinstance(dim, tuple) else (dim,)
            bounds = _BOUNDS.get((shape, kdim))
            if bounds is None:  # read-only for the kernel: one per launch shape serves every call and thread
                if len(_BOUNDS) > 4096:
                    _BOUNDS.clear()
                bounds = _BOUNDS[(shape, kdim)] = bounds_of(shape, kdim)
            hook(ctypes.byref(bounds), ctypes.byref(args))
            return
        if d is False and (kernel, device) in _LOADED:
            with _DIRECT_LOCK:
                if kernel not in _DIRECT:
                    _DIRECT[kernel] = _describe(kernel, dim, inputs)
            return run(kernel, dim, inputs, device)
    gpu = {} if device == "cpu" else {"block_dim": gpu_block}
    wp.launch(kernel, dim=dim, inputs=_launchable(inputs), device=device, record_tape=False, **gpu)
    _LOADED.add((kernel, device))


MIN_SPLIT = 16384  # fewer work items than this run as one launch: a thread hand-off costs ~0.05-0.1 ms


def launch(kernel, dim, inputs: list, offset_at: int, device: str, work: int | None = None,
           gpu_block: int = 256) -> None:
    """wp.launch over `dim` (an int, or (rows, cols) split by rows) with inputs[offset_at] = the first item.

    Warp's CPU backend runs a launch on one thread and its ctypes call releases the GIL, so on the CPU the range is
    cut into one contiguous part per core and each part launched from its own Python thread (same kernel, its
    offset as an argument; the parts write disjoint outputs). The first launch of a kernel compiles and loads its
    module, so it runs whole on the calling thread, and so does a launch over fewer than MIN_SPLIT `work` items
    (points or pixels; default: the rows). CUDA: a single launch of `gpu_block` threads per block (Warp's
    default 256; docs/gpu.md has each kernel's registers and the occupancy they allow).
    """
    rows = dim if isinstance(dim, int) else dim[0]
    parts = min(_cpu_threads() if device == "cpu" else 1, rows)
    if (work if work is not None else rows) < MIN_SPLIT:
        parts = 1
    key = (kernel, device)
    if parts <= 1 or key not in _LOADED:  # always on CUDA (parts == 1)
        args = list(inputs)
        args[offset_at] = 0
        run(kernel, dim, args, device, gpu_block)
        return
    cuts = [rows * k // parts for k in range(parts + 1)]

    def part(k: int) -> None:
        args = list(inputs)
        args[offset_at] = cuts[k]
        n = cuts[k + 1] - cuts[k]
        run(kernel, n if isinstance(dim, int) else (n, *dim[1:]), args, device)

    pool = _pool(max(1, _cpu_threads() - 1))
    futures = [pool.submit(part, k) for k in range(1, parts)]
    part(0)
    for f in futures:
        f.result()
