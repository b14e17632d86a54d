"""Warp's CPU launches split over Python threads (kernels/_warp/launch.py `launch`) give exactly the single-launch
result: the parts cover disjoint items / reduction blocks, so the sums and indices are bitwise equal."""

import os
import sys
import threading

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import icp as K
from swarmsplat.kernels import se3
from swarmsplat.registration import synthetic


@pytest.fixture
def warp_cpu(monkeypatch):
    kernels.use("warp", "cpu")
    from swarmsplat.kernels._warp import launch as W

    def run_with(parts: int, fn):
        monkeypatch.setattr(W, "_cpu_threads", lambda: parts)
        monkeypatch.setattr(W, "MIN_SPLIT", 0)  # split even these small frames
        fn()  # the first launch of a kernel runs whole (it compiles / loads the module)
        return fn()

    return run_with


def test_split_launches_equal_one_launch(warp_cpu):
    cam, (_, ds), (_, dt), T = synthetic.pair(160, 120)
    Tp = torch.from_numpy(se3.exp(np.array([0.004, -0.003, 0.002, 0.01, -0.005, 0.008])) @ T)

    def run():
        tv, tn = K.vertices_normals_from_depth(torch.from_numpy(dt), cam)
        sv, sn = K.vertices_normals_from_depth(torch.from_numpy(ds), cam)
        src, srcn = sv.reshape(-1, 3), sn.reshape(-1, 3)
        ne = K.projective_normal_equations(src, Tp, tv, tn, cam, max_distance=0.05, source_normals=srcn,
                                           max_angle_deg=40.0, robust="huber", robust_scale=0.02)
        idx = K.associate_projective(src, Tp, tv, tn, cam, max_distance=0.05)
        tp = tv.reshape(-1, 3)[tv.reshape(-1, 3)[:, 2] > 0].contiguous()
        grid = K.PointGrid(tp, 0.05)
        nn = K.associate_nearest(src, Tp, grid, max_distance=0.05)
        mom = K.cloud_moments(grid, tp, 0.05)
        return tv, tn, ne, idx, nn, mom

    one = warp_cpu(1, run)
    for parts in (2, 3):
        many = warp_cpu(parts, run)
        assert torch.equal(one[0], many[0]) and torch.equal(one[1], many[1])
        assert torch.equal(one[2].JtJ, many[2].JtJ) and torch.equal(one[2].Jtr, many[2].Jtr)
        assert one[2].count == many[2].count > 1000 and one[2].cost == many[2].cost
        assert torch.equal(one[3], many[3]) and torch.equal(one[4], many[4]) and torch.equal(one[5], many[5])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_lower_priority_thread_launches_on_its_own_pool(warp_cpu):
    """A thread that lowered its priority (the real-time mapping worker) runs its parts on a pool of that nice value,
    not in the queue of a normal thread's pool, with the same results."""
    from swarmsplat.kernels._warp import launch as W

    cam, (_, ds), (_, dt), T = synthetic.pair(160, 120)

    def run():
        tv, tn = K.vertices_normals_from_depth(torch.from_numpy(dt), cam)
        sv, sn = K.vertices_normals_from_depth(torch.from_numpy(ds), cam)
        return tv, tn, K.projective_normal_equations(sv.reshape(-1, 3), torch.from_numpy(T), tv, tn, cam,
                                                     max_distance=0.05, robust="huber", robust_scale=0.02)

    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    mine = warp_cpu(2, run)
    out = {}

    def low():
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(19, base + 5))
        out["result"] = run()
        pool = W._pool(1)
        out["pool"] = pool
        out["worker_nice"] = pool.submit(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result()

    t = threading.Thread(target=low)
    t.start()
    t.join()
    assert out["pool"] is not W._pool(1)
    assert out["worker_nice"] == min(19, base + 5)
    theirs = out["result"]
    assert torch.equal(mine[0], theirs[0]) and torch.equal(mine[1], theirs[1])
    assert torch.equal(mine[2].JtJ, theirs[2].JtJ) and mine[2].count == theirs[2].count > 1000
