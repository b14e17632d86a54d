"""slam.dense.frames: resizing a frame's depth (block means that drop depth edges)."""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.dense.frames import RGBD, _block_depth, _downsample_depth


def test_halving_depth_equals_the_block_rule_bit_for_bit():
    rng = np.random.default_rng(3)
    d = rng.uniform(0.4, 6.0, (48, 64)).astype(np.float32)
    d[:, 40:] = 2.0 + 1e-3 * rng.random((48, 24), dtype=np.float32)  # a smooth region: blocks stay valid
    d[rng.random(d.shape) < 0.2] = 0.0
    out = _downsample_depth(d, 32, 24)
    assert out.dtype == np.float32 and np.array_equal(out, _block_depth(d, 2))
    assert (out[:, 20:] > 0).mean() > 0.9 and (out[:, :20] > 0).mean() < 0.5  # edges dropped, smooth kept


def test_block_rule_keeps_a_lone_valid_pixel_and_drops_an_edge():
    d = np.zeros((4, 4), np.float32)
    d[0, 1] = 1.5  # block (0, 0): one valid pixel
    d[2:, 2:] = [[1.0, 1.0], [1.0, 2.0]]  # block (1, 1): a depth edge
    d[2:, :2] = 3.0  # block (1, 0): flat
    out = RGBD(np.zeros((4, 4, 3), np.uint8), d, PinholeCamera(4.0, 4.0, 1.5, 1.5, 4, 4)).resized(2).depth
    assert out.tolist() == [[1.5, 0.0], [3.0, 0.0]]
