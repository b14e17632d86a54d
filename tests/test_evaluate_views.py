"""Rendering evaluation at the working and the input resolution (slam.metrics.views) on the analytic scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.metrics.views import mean_scores, resolutions, score_frame, score_view
from swarmsplat.slam.dense.frames import make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.mapping.mapper import MapKeyframe, Mapper
from swarmsplat.slam.metrics import psnr

import slam_scene


@pytest.fixture(scope="module")
def fitted():
    """A 128x96 input frame; the pipeline works at 64 px and maps there (mapping.max_width 0 = working)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    kernels.use("warp", "cpu")
    cam = slam_scene.camera(128, 96)
    cfg = SlamConfig().override({"image": {"max_width": 64}, "mapping": {"seed_stride": 1}})
    color, depth = slam_scene.render(np.eye(4), cam)
    work = make_rgbd(color, depth, cam, min_depth=0.1, max_depth=10.0).resized(cfg.image.max_width)
    gm = GaussianMap()
    sm = gm.new_submap(np.eye(4))
    Mapper(cfg.mapping).map(gm, sm, [MapKeyframe(np.eye(4), work.resized(cfg.mapping.max_width))], 40)
    yield cam, cfg, sm.params, color, depth
    torch.set_num_threads(n)


def test_resolutions_follow_image_max_width():
    cam = slam_scene.camera(640, 480)
    cfg = SlamConfig()
    assert cfg.mapping.max_width == 0  # mapping at the working resolution by default
    assert resolutions(cam, cfg) == {"render_resolution": [320, 240], "input_resolution": [640, 480]}
    assert resolutions(cam, cfg.override({"image": {"max_width": 1280}}))["render_resolution"] == [640, 480]
    assert resolutions(slam_scene.camera(160, 120), cfg)["render_resolution"] == [160, 120]


def test_scores_at_both_resolutions(fitted):
    cam, cfg, params, color, depth = fitted
    s, work, rendered = score_view(params, np.eye(4), color, depth, cam, cfg)
    assert rendered.shape == (48, 64, 3) and work.camera.width == 64
    # The working figures are the plain metrics of the render against the area-downsampled input.
    assert s["psnr"] == pytest.approx(psnr(rendered.permute(2, 0, 1), work.color_tensor().permute(2, 0, 1)))
    full = make_rgbd(color, depth, cam, min_depth=0.1, max_depth=10.0)
    s_in, _ = score_frame(params, np.eye(4), full)
    assert s["psnr_input_resolution"] == pytest.approx(s_in["psnr"])
    # A map fitted at 64 px is sharper at 64 px than against the 128 px input, and both are a real fit.
    assert s["psnr"] > s["psnr_input_resolution"] > 15, s
    assert 0 < s["depth_l1_input_resolution"] < 0.1 and s["ssim"] > s["ssim_input_resolution"]
    # A wrong pose scores worse at both resolutions.
    from swarmsplat.kernels import se3

    bad, _, _ = score_view(params, se3.exp(np.array([0.0, 0.05, 0.0, 0.05, 0.0, 0.0])), color, depth, cam, cfg)
    assert bad["psnr"] < s["psnr"] - 3 and bad["psnr_input_resolution"] < s["psnr_input_resolution"] - 3


def test_mean_scores_skips_missing_values():
    m = mean_scores([{"psnr": 20.0, "depth_l1": None}, {"psnr": 30.0, "depth_l1": 0.1}, {"psnr": float("inf")}])
    assert m == {"psnr": 25.0, "depth_l1": 0.1}
    assert mean_scores([{"psnr": None}]) == {"psnr": None}
