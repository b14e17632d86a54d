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
