"""The process's memory and the C allocator (glibc on Linux): what a run asks of it, nothing elsewhere.

    from swarmsplat.kernels.memory import glibc, trim_heap
    trim_heap()  # the heap's free pages back to the system
"""

from __future__ import annotations

import ctypes
import functools
import sys


@functools.lru_cache(maxsize=1)
def glibc():
    """The C library as a ctypes handle when it is glibc on Linux (mallopt, malloc_trim), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim, libc.mallopt  # noqa: B018 - glibc's, absent from musl
    except (OSError, AttributeError):
        return None
    return libc


def trim_heap() -> bool:
    """Hand the heap's free pages back to the system (glibc malloc_trim(0): every arena, holes between live
    blocks included). The agent calls it once per finished submap (kernels.malloc_trim): a submap's tensors, its
    keyframes' images and the loop closer's temporaries are freed by then, and without a trim glibc keeps the
    pages of a heap that a few live blocks pin, so a long mission's resident memory climbs a little with every
    submap. 1-12 ms a call (a generated 640x480 run). Nothing without glibc; returns whether memory was released."""
    libc = glibc()
    return bool(libc.malloc_trim(0)) if libc is not None else False
