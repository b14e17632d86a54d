"""The allocator: slam.run.runtime.tame_allocator, the glibc mmap threshold a run may fix
(kernels.malloc_mmap_threshold_kb; run in child processes: the setting is the whole process's); kernels.memory.trim_heap,
and the trim each driver's agent asks for once per finished submap (kernels.malloc_trim)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time

import pytest

from test_run_checkpoint import QUICK as CHECKPOINT_QUICK

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


# ---- the trim in the drivers: once per finished submap, whichever driver steps the agent ------------------------

# tiny images, few iterations; a keyframe every 3 frames, a submap every 2 keyframes (as the checkpoint tests)
DRIVER_QUICK = {**CHECKPOINT_QUICK, "loop_closure": {"enabled": False}}


@pytest.fixture(scope="module")
def driver_sequence(tmp_path_factory):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("trim")
    return generate(root, GeneratorConfig.preset("tiny", agents=1, frames=18, seed=1)) / "agent_0"


@pytest.fixture
def trims(monkeypatch) -> list[str]:
    """Every heap trim the agents ask for, by the thread that asked (the real trim still runs)."""
    import threading

    from swarmsplat.kernels import memory
    from swarmsplat.slam.dense import agent as dense_agent
    from swarmsplat.slam.run.realtime import agent as realtime_agent

    calls: list[str] = []

    def counted() -> bool:
        calls.append(threading.current_thread().name)
        return memory.trim_heap()

    monkeypatch.setattr(dense_agent, "trim_heap", counted)
    monkeypatch.setattr(realtime_agent, "trim_heap", counted)
    return calls


def _cfg(**changes):
    from swarmsplat.slam.config import SlamConfig

    return SlamConfig().override(DRIVER_QUICK).override(changes)


@pytest.mark.parametrize("on", [True, False])
def test_a_sequence_run_trims_once_per_finished_submap(driver_sequence, tmp_path, trims, on):
    from swarmsplat.slam.run.sequence import run_sequence

    m = run_sequence(driver_sequence, tmp_path / "run", _cfg(kernels={"malloc_trim": on}), progress=False)
    assert m["submaps"] >= 3  # at least two finished
    assert len(trims) == (m["submaps"] - 1 if on else 0)


def test_a_team_run_trims_once_per_finished_submap_of_each_agent(driver_sequence, tmp_path, trims):
    from swarmsplat.slam.cli import main

    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(_cfg().to_yaml())
    assert main(["run", str(driver_sequence), "--split", "0:9,9:18", "--out", str(tmp_path / "team"), "--config",
                 str(cfg), "--quiet"]) == 0
    m = json.loads((tmp_path / "team" / "metrics.json").read_text())
    finished = sum(a["submaps"] - 1 for a in m["agents"])
    assert finished >= 2 and len(trims) == finished


def test_a_live_run_trims_once_per_finished_submap(driver_sequence, tmp_path, trims):
    """slam.run.live.run_live (`swarmsplat agent --source zenoh/...`) with the frames handed over in process."""
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.io.live import SourceStats
    from swarmsplat.slam.run.live import run_live

    seq = load_sequence(driver_sequence)

    class Source:
        name, stats = "live", SourceStats()

        def wait_camera(self, timeout):
            return seq.camera

        def frames(self, **_):
            for i in range(len(seq)):
                now = time.monotonic()
                yield seq[i], now, now

    m = run_live(Source(), tmp_path / "live", _cfg(), progress=False)
    assert m["frames_tracked"] == len(seq) and m["submaps"] >= 3
    assert len(trims) == m["submaps"] - 1


def test_a_realtime_run_trims_once_per_finished_submap_on_its_worker(driver_sequence, tmp_path, trims):
    from swarmsplat.slam.run.realtime.run import run_realtime

    cfg = _cfg(runtime={"realtime": True, "rate": 3})  # slow enough that, on an idle machine, every frame is tracked
    m = run_realtime(driver_sequence, tmp_path / "rt", cfg, progress=False)
    rt = m["realtime"]  # a loaded machine may drop a frame the tracker could not take in time: counted, not lost
    assert rt["frames_tracked"] + rt["frames_dropped"] == 18 and rt["frames_tracked"] >= 12 and m["submaps"] >= 3
    assert len(trims) == m["submaps"] - 1 and all(t.endswith("-mapping") for t in trims), trims
