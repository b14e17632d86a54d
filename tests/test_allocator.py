"""slam.run.runtime.tame_allocator: the glibc mmap threshold a run may fix (kernels.malloc_mmap_threshold_kb). Run
in child processes: the setting is the whole process's."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

CODE = "from swarmsplat.slam.run.runtime import tame_allocator; print(tame_allocator({kb}))"


def _run(kb: int, **env) -> str:
    out = subprocess.run([sys.executable, "-c", CODE.format(kb=kb)], capture_output=True, text=True, check=True,
                         env={**os.environ, **env})
    return out.stdout.strip()


def test_zero_leaves_the_allocator_alone():
    assert _run(0) == "False"


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                    reason="mallopt is glibc's")
def test_threshold_is_set_unless_the_environment_set_one():
    assert _run(128) == "True"
    assert _run(128, MALLOC_MMAP_THRESHOLD_="262144") == "False"


TRIM = """
import ctypes
from swarmsplat.kernels.memory import trim_heap

def rss_kb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))

libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
libc.mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD 1 MB: the 64 kB blocks below come from the heap
libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD high: free() alone never gives the heap's top back
blocks = [libc.malloc(64 << 10) for _ in range(2000)]  # 125 MB of heap
for b in blocks:
    ctypes.memset(b, 1, 64 << 10)
for b in blocks[:-1]:  # the last block stays: the heap cannot shrink from its top
    libc.free(b)
before = rss_kb()
released = trim_heap()
print(released, before - rss_kb())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                    reason="malloc_trim is glibc's")
def test_trim_hands_freed_heap_pages_back():
    """A heap pinned by its last block keeps ~125 MB of freed pages resident; trim_heap (kernels.malloc_trim)
    returns them to the system."""
    out = subprocess.run([sys.executable, "-c", TRIM], capture_output=True, text=True, check=True)
    released, dropped_kb = out.stdout.split()
    assert released == "True"
    assert int(dropped_kb) > 100_000
