"""The map refinement's learning-rate schedule (MapRefineConfig.lr_final_scale): geometric from the start rates to
lr_final_scale times them at the last step, and what the optimiser is actually given, for both optimisers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import swarmsplat.slam.dense.mapping.refine_merged as mr
from swarmsplat.kernels import use_reference
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.config import MappingConfig, MapRefineConfig
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.mapping.refine_merged import RefineView, lr_factor, refine_map
from swarmsplat.slam.dense.render import viewmat_from_pose
from swarmsplat.slam.dense.mapping.selective_adam import SelectiveAdam


def test_lr_factor_is_geometric_from_one_to_final():
    f = [lr_factor(0.3, i, 5) for i in range(5)]
    assert f[0] == 1.0 and f[-1] == pytest.approx(0.3)
    assert np.allclose(np.diff(np.log(f)), np.log(0.3) / 4)
    assert lr_factor(0.3, 0, 1) == 1.0  # a single step keeps the start rate
    assert all(lr_factor(1.0, i, 7) == 1.0 for i in range(7))


def _scene():
    g = torch.Generator().manual_seed(0)
    n = 40
    pts = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 2.0 + 0.2 * torch.rand(n, 1, generator=g)], 1)
    p = GaussianParams.from_points(pts, torch.rand(n, 3, generator=g), torch.full((n,), 0.05))
    cam = PinholeCamera(40.0, 40.0, 15.5, 11.5, 32, 24)
    view = RefineView(viewmat_from_pose(np.eye(4)), torch.rand(24, 32, 3, generator=g), torch.full((24, 32), 2.0),
                      cam)
    return p, [view]


@pytest.mark.parametrize("optimizer", ["adam", "selective"])
def test_the_optimiser_gets_the_decayed_rates(monkeypatch, optimizer):
    seen: list[list[float]] = []
    if optimizer == "adam":
        make = mr.make_optimizer

        def spy(*a, **k):
            opt = make(*a, **k)
            opt.register_step_pre_hook(lambda o, *_: seen.append([g["lr"] for g in o.param_groups]))
            return opt

        monkeypatch.setattr(mr, "make_optimizer", spy)
    else:
        step = SelectiveAdam.step

        def spy_step(self, idx, grads):
            seen.append(list(self.lrs))
            return step(self, idx, grads)

        monkeypatch.setattr(SelectiveAdam, "step", spy_step)
    p, views = _scene()
    cfg = MapRefineConfig(lr_final_scale=0.25, optimizer=optimizer, min_contribution=0.0, iterations_per_keyframe=5)
    with use_reference():
        refine_map(p, views, cfg, MappingConfig(), iterations=5)
    lrs = np.array(seen)
    assert lrs.shape[0] == 5
    assert np.allclose(lrs / lrs[0], [[lr_factor(0.25, i, 5)] for i in range(5)])
    assert lrs[0][0] == pytest.approx(MappingConfig().lr_means * cfg.lr_scale)


def test_views_of_stored_keyframes_decode_through_a_bounded_cache():
    """A refinement view of a packed keyframe reads the same images as the frame itself; the shared cache keeps
    decoded views up to its byte bound, least recently used dropped first."""
    from swarmsplat.slam.dense.frames import RGBD
    from swarmsplat.slam.dense.mapping.refine_merged import RefineView, ViewCache
    from swarmsplat.slam.dense.packed import pack
    from swarmsplat.kernels.camera import PinholeCamera

    cam = PinholeCamera(40.0, 40.0, 16.0, 12.0, 32, 24)
    rng = np.random.default_rng(0)
    frames = [pack(RGBD(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
                        rng.uniform(0.5, 3.0, (24, 32)).astype(np.float32), cam)) for _ in range(3)]
    one = 24 * 32 * 4 * (3 + 1)  # bytes of one decoded view (float32 colour and depth)
    cache = ViewCache(2 * one)
    views = [RefineView(viewmat_from_pose(np.eye(4)), None, None, cam, frame=f, cache=cache) for f in frames]
    for v, f in zip(views, frames):
        assert torch.equal(v.color, f.color_tensor()) and torch.equal(v.depth, f.depth_tensor())
    assert cache.decoded == 3 and cache.bytes == 2 * one  # the first view was dropped for the third
    views[2].color, views[1].depth  # noqa: B018 - hits
    assert cache.decoded == 3
    views[0].color  # noqa: B018 - dropped before: decoded again
    assert cache.decoded == 4 and cache.bytes <= 2 * one
    assert torch.equal(RefineView(viewmat_from_pose(np.eye(4)), None, None, cam, frame=frames[0]).depth,
                       frames[0].depth_tensor())  # no cache: decoded at each read


def test_the_exposures_take_the_refinements_own_step_and_prior(monkeypatch):
    """MapRefineConfig.exposure_lr / exposure_regulariser, not ExposureConfig's (mapping's), drive the keyframes'
    exposures in the refinement: the optimiser gets the refinement's step at every step, and the prior's weight is
    the refinement's."""
    from swarmsplat.slam.config import ExposureConfig
    from swarmsplat.slam.dense.mapping.mapper import ExposureSteps

    seen: list[tuple[list[float], float]] = []
    step = ExposureSteps.step

    def spy(self):
        seen.append(([g["lr"] for g in self.opt.param_groups], self.cfg.regulariser))
        return step(self)

    monkeypatch.setattr(ExposureSteps, "step", spy)
    p, views = _scene()
    e = np.array([-0.2, -0.1, -0.3, 0.0, 0.0, 0.0])
    views = [views[0].at(exposure=np.zeros(6)), views[0].at(exposure=e)]  # the first holds the gauge
    for v in views:
        v.exposure_prior = v.exposure.copy()
    cfg = MapRefineConfig(exposure_lr=0.03, exposure_regulariser=0.02, lr_final_scale=0.25, min_contribution=0.0,
                          iterations_per_keyframe=3)
    with use_reference():
        _, _, st = refine_map(p, views, cfg, MappingConfig(), exposure=ExposureConfig(lr=1e-4, regulariser=5.0))
    assert len(seen) == 6
    assert all(lrs == [0.03] and reg == 0.02 for lrs, reg in seen)
    assert np.array_equal(st.exposures[0], np.zeros(6))  # the gauge stays
    assert np.abs(st.exposures[1] - e).max() > 1e-3  # moved at the refinement's step, not at mapping's 1e-4
