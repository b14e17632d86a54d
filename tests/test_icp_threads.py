"""Warp's CPU launches split over Python threads (kernels/_warp/launch.py `launch`) give exactly the single-launch
result: the parts cover disjoint items / reduction blocks, so the sums and indices are bitwise equal."""

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
