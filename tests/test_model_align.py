"""slam.model_align: the tracker's frame-to-model Gauss-Newton against a prepared model view (exact ray-cast
views of the analytic scene, so only the alignment is tested)."""

from __future__ import annotations

import numpy as np
import pytest

import kernels
from kernels import se3
from slam.frames import RGBD, make_rgbd
from slam.model_align import ModelTarget, align_to_model

import slam_scene


@pytest.fixture(scope="module")
def pair():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    kernels.use("warp", "cpu")
    cam = slam_scene.camera(96, 72)
    T_view = se3.exp(np.array([0.0, 0.02, 0.0, 0.0, 0.0, 0.0]))
    T_true = se3.exp(np.array([0.0, 0.03, 0.0, 0.02, 0.0, 0.01]))
    frame = lambda T: make_rgbd(*slam_scene.render(T, cam), cam, min_depth=0.1, max_depth=10.0)  # noqa: E731
    yield cam, T_view, T_true, frame(T_view), frame(T_true)
    torch.set_num_threads(n)


def _err(T_true, T):
    E = se3.inverse(T_true) @ T
    return np.linalg.norm(E[:3, 3]), np.degrees(se3.rotation_angle(E[:3, :3]))


@pytest.mark.parametrize("strides", [[1], [2, 1]])
def test_align_to_model_recovers_the_relative_pose(pair, strides):
    cam, T_view, T_true, view, frame = pair
    truth = se3.inverse(T_view) @ T_true  # T_view_cam
    start = truth @ se3.exp(np.array([0.01, -0.01, 0.005, 0.01, -0.008, 0.01]))
    target = ModelTarget(view, strides)
    r = align_to_model(frame, target, start, iterations=5, photometric_weight=0.3, max_distance=0.05)
    (t0, a0), (t1, a1) = _err(truth, start), _err(truth, r.T_view_cam)
    assert r.success and 0 < r.iterations <= 5 * len(strides) and r.count > 1000 and np.isfinite(r.rmse)
    assert t1 < 0.15 * t0 and a1 < 0.1 * a0, (t0, t1, a0, a1)
    # The prepared target is only read: aligning again gives the same pose as a freshly built one.
    again = align_to_model(frame, ModelTarget(view, strides), start, iterations=5, photometric_weight=0.3,
                           max_distance=0.05)
    np.testing.assert_allclose(again.T_view_cam, align_to_model(frame, target, start, iterations=5,
                               photometric_weight=0.3, max_distance=0.05).T_view_cam, atol=1e-9)


def test_align_to_model_fails_cleanly(pair):
    cam, T_view, T_true, view, frame = pair
    start = se3.inverse(T_view) @ T_true
    empty = RGBD(frame.color, np.zeros_like(frame.depth), cam)
    r = align_to_model(empty, ModelTarget(view, [1]), start, iterations=3, photometric_weight=0.3, max_distance=0.05)
    assert not r.success and np.array_equal(r.T_view_cam, start)
    with pytest.raises(ValueError, match="camera"):
        align_to_model(frame.resized(48), ModelTarget(view, [1]), start, iterations=1, photometric_weight=0.3,
                       max_distance=0.05)


def test_tracker_drops_a_model_view_that_disagrees_with_its_keyframe(pair):
    """The self-check behind tracking.max_view_bias: a view rendered where its keyframe is passes; a view 1 cm
    off the keyframe (a map that does not fit its own keyframe) is refused."""
    from slam.config import SlamConfig
    from slam.tracker import Tracker

    cam, T_view, T_true, view, frame = pair
    tc = SlamConfig().tracking.model_copy(update={"refine_max_width": cam.width})
    tr = Tracker(tc)
    tr._prev = view  # the keyframe the view was rendered at
    assert tr._view_agrees(view, ModelTarget(view, [1]))
    shifted = make_rgbd(*slam_scene.render(T_view @ se3.exp(np.array([0, 0, 0, 0.01, 0, 0.0])), cam), cam,
                        min_depth=0.1, max_depth=10.0)
    assert not tr._view_agrees(shifted, ModelTarget(shifted, [1]))
