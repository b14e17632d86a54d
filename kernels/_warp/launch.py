"""Warp CPU launches split over the cores: Warp's CPU backend runs one launch on one thread, and its ctypes call
releases the GIL, so a launch over many items is cut into one contiguous part per core, each launched from its own
Python thread (the ICP kernels use it; results are bitwise equal to one launch, tests/test_icp_threads.py)."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

_POOL: ThreadPoolExecutor | None = None
_POOL_PID = -1
_POOL_LOCK = threading.Lock()
_LOADED: set = set()  # (kernel, device) launched at least once: compiled and loaded, safe to launch from threads


def _cpu_threads() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _pool(workers: int) -> ThreadPoolExecutor:
    # One pool per process: a forked child inherits the pool object but not its threads, so it makes its own.
    global _POOL, _POOL_PID
    with _POOL_LOCK:
        if _POOL is None or _POOL_PID != os.getpid():
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="swarmsplat-warp-cpu")
            _POOL_PID = os.getpid()
    return _POOL


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
        gpu = {} if device == "cpu" else {"block_dim": gpu_block}
        wp.launch(kernel, dim=dim, inputs=args, device=device, record_tape=False, **gpu)
        _LOADED.add(key)
        return
    cuts = [rows * k // parts for k in range(parts + 1)]

    def part(k: int) -> None:
        args = list(inputs)
        args[offset_at] = cuts[k]
        n = cuts[k + 1] - cuts[k]
        wp.launch(kernel, dim=n if isinstance(dim, int) else (n, *dim[1:]), inputs=args, device=device,
                  record_tape=False)

    pool = _pool(max(1, _cpu_threads() - 1))
    futures = [pool.submit(part, k) for k in range(1, parts)]
    part(0)
    for f in futures:
        f.result()
