"""slam.dense.team.held: the bytes a team holds, each buffer once."""

import numpy as np
import torch

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.submaps import Keyframe
from swarmsplat.slam.dense.team.held import held_bytes


def _kf(i, rgbd, small):
    return Keyframe(i, i, float(i), 0, np.eye(4), rgbd, small)


def test_counts_each_buffer_once_through_our_objects_and_containers():
    cam = PinholeCamera(50.0, 50.0, 20.0, 15.0, 40, 30)
    color = np.zeros((30, 40, 3), np.uint8)
    depth = np.ones((30, 40), np.float32)
    big = RGBD(color, depth, cam)
    small = RGBD(color[::2, ::2], depth[::2, ::2], cam)  # views of the same buffers: not counted again
    kfs = [_kf(0, big, small), _kf(1, None, small)]
    pose_bytes = 2 * 16 * 8  # each keyframe's T_local_cam
    assert held_bytes(kfs) == color.nbytes + depth.nbytes + pose_bytes
    t = torch.zeros(100, dtype=torch.float32)
    extra = {"pending": {3: b"x" * 1000}, "tensors": [t, t[10:]], "ints": {1, 2, 3}}
    assert held_bytes(kfs, extra) == color.nbytes + depth.nbytes + pose_bytes + 1000 + 400


def test_objects_of_other_packages_are_not_entered():
    class Foreign:  # a test module's class stands for another package's object
        def __init__(self):
            self.a = np.zeros(1000)

    assert held_bytes([Foreign()]) == 0
    assert held_bytes([np.zeros(10)]) == 80
