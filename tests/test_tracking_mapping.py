"""Tracking, mapping and submap transforms on a tiny analytic scene (64x48, a few thousand Gaussians)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import kernels
from kernels import se3
from slam.config import SlamConfig
from slam.frames import RGBD, make_rgbd
from slam.gaussian_map import GaussianMap, transform_params
from slam.mapper import MapKeyframe, Mapper
from slam.render import render, viewmat_from_pose
from slam.tracker import refine_pose

import slam_scene


@pytest.fixture(scope="module")
def warp_cpu():
    # One torch thread, as `swarmsplat run` uses: the per-call tensors are small (see KernelsConfig.torch_threads).
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield kernels.use("warp", "cpu")
    torch.set_num_threads(n)


def _frame(T_world_cam, cam):
    return make_rgbd(*slam_scene.render(T_world_cam, cam), cam, min_depth=0.1, max_depth=10.0)


@pytest.fixture(scope="module")
def mapped(warp_cpu):
    """A submap fitted to one 64x48 view at the origin."""
    cam = slam_scene.camera(64, 48)
    cfg = SlamConfig().override({"mapping": {"seed_stride": 1}})
    gm = GaussianMap()
    sm = gm.new_submap(np.eye(4))
    stats = Mapper(cfg.mapping).map(gm, sm, [MapKeyframe(np.eye(4), _frame(np.eye(4), cam))], 30)
    return cam, cfg, gm, sm, stats


def test_mapping_lowers_the_loss(mapped):
    *_, stats = mapped
    assert stats.added == 64 * 48  # stride 1, every pixel valid, empty map
    assert stats.loss_last < 0.5 * stats.loss_first


def test_tracking_recovers_a_perturbed_pose(mapped):
    cam, cfg, _, sm, _ = mapped
    T_true = se3.exp(np.array([0.0, 0.03, 0.0, 0.02, 0.0, 0.01]))
    with torch.no_grad():
        out = render(sm.params, viewmat_from_pose(T_true), cam)
    frame = RGBD((out.color.clamp(0, 1).numpy() * 255).round().astype(np.uint8),
                 (out.depth_normalised * (out.alpha > 0.5)).numpy().astype(np.float32), cam)
    T0 = T_true @ se3.exp(np.array([0.02, -0.02, 0.01, 0.02, -0.015, 0.02]))
    tc = cfg.tracking.model_copy(update={"refine_max_width": 64, "pyramid_levels": 1, "iterations": 50})
    T, iters, _ = refine_pose(sm.params, frame, T0, tc)
    err = lambda A: se3.inverse(T_true) @ A  # noqa: E731
    t0, t1 = np.linalg.norm(err(T0)[:3, 3]), np.linalg.norm(err(T)[:3, 3])
    r0, r1 = se3.rotation_angle(err(T0)[:3, :3]), se3.rotation_angle(err(T)[:3, :3])
    assert 0 < iters <= 50
    assert t1 < 0.2 * t0 and t1 < 0.006, (t0, t1)
    assert r1 < 0.1 * r0, (np.degrees(r0), np.degrees(r1))


def test_mapping_fills_a_hole(warp_cpu):
    cam = slam_scene.camera(64, 48)
    cfg = SlamConfig().override({"mapping": {"seed_stride": 1}})
    full = _frame(np.eye(4), cam)
    holed = RGBD(full.color, full.depth.copy(), cam)
    holed.depth[16:32, 24:44] = 0.0  # no depth -> no seeds there
    gm = GaussianMap()
    sm = gm.new_submap(np.eye(4))
    mapper = Mapper(cfg.mapping)
    mapper.map(gm, sm, [MapKeyframe(np.eye(4), holed)], 15)
    vm = viewmat_from_pose(np.eye(4))
    with torch.no_grad():
        before = render(sm.params, vm, cam).alpha[20:28, 30:38].mean()
    n0 = len(sm)
    stats = mapper.map(gm, sm, [MapKeyframe(np.eye(4), holed), MapKeyframe(np.eye(4), full)], 15)
    with torch.no_grad():
        after = render(sm.params, vm, cam).alpha[20:28, 30:38].mean()
    assert stats.added >= 0.8 * 16 * 20 and len(sm) > n0
    assert before < 0.3 and after > 0.9, (float(before), float(after))


def test_submap_transform_moves_its_renders_exactly(mapped):
    cam, _, _, sm, _ = mapped
    T_view = se3.exp(np.array([0.02, -0.05, 0.01, 0.1, 0.0, -0.1]))  # camera in the submap's local frame
    D = se3.exp(np.array([0.3, -0.4, 0.2, 1.5, -0.7, 2.0]))  # move the whole submap
    moved = transform_params(sm.params, D)
    with torch.no_grad():
        a = render(sm.params, viewmat_from_pose(T_view), cam)
        b = render(moved, viewmat_from_pose(D @ T_view), cam)
    assert float(a.alpha.mean()) > 0.5
    # Equal up to float32 rounding of the moved means (metres away from the origin); a rounding flip at the
    # 1/255 alpha cut-off may move a single pixel by ~1e-3.
    for x, y in [(a.color, b.color), (a.depth, b.depth), (a.alpha, b.alpha)]:
        d = (x - y).abs()
        assert float(d.max()) < 5e-3 and float((d > 1e-4).float().mean()) < 0.01, (float(d.max()), float(d.mean()))


def test_contributions_see_hidden_gaussians(warp_cpu):
    """A small Gaussian right behind an opaque larger one contributes (almost) nothing to the view; the front one
    a lot; one outside the view nothing."""
    from slam.gaussian_map import GaussianParams
    from slam.map_refine import RefineView, contributions

    cam = slam_scene.camera(64, 48)
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.2], [5.0, 0.0, 2.0]])  # front, hidden behind it, out of view
    g = GaussianParams.from_points(pts, torch.full((3, 3), 0.5), torch.tensor([0.1, 0.03, 0.1]), opacity=0.99)
    view = RefineView(viewmat_from_pose(np.eye(4)), torch.zeros(48, 64, 3), torch.zeros(48, 64), cam)
    w = contributions(g, [view])
    assert w[0] > 10.0 and w[1] < 0.05 * w[0] and w[2] == 0.0


def test_refine_map_lowers_the_loss_and_keeps_order(mapped):
    """Refining a submap over a second view it was never fitted to lowers the loss on that view; 0 steps is a
    no-op; the kept Gaussians come back in their input order."""
    from slam.map_refine import RefineView, iteration_budget, refine_map

    cam, cfg, gm, sm, _ = mapped
    T2 = se3.exp(np.array([0.0, 0.08, 0.0, 0.06, 0.0, 0.0]))
    f2 = _frame(T2, cam)
    views = [RefineView(viewmat_from_pose(T), f.color_tensor(), f.depth_tensor(), f.camera)
             for T, f in ((np.eye(4), _frame(np.eye(4), cam)), (T2, f2))]

    def loss(p):
        with torch.no_grad():
            out = render(p, views[1].viewmat, cam)
        return float((out.color - views[1].color).abs().mean())

    rc = cfg.map_refine.model_copy(update={"iterations_per_keyframe": 15})
    assert iteration_budget(rc, 2) == 30
    assert iteration_budget(rc.model_copy(update={"max_iterations": 7}), 2) == 7
    same, keep0, st0 = refine_map(sm.params, views, rc, cfg.mapping, iterations=0)
    assert st0.iterations == 0 and bool(keep0.all()) and torch.equal(same.means, sm.params.means)
    refined, keep, st = refine_map(sm.params, views, rc, cfg.mapping)
    assert st.iterations == 30 and len(refined) == int(keep.sum()) and int(keep.sum()) > 0.5 * len(sm.params)
    assert loss(refined) < 0.9 * loss(sm.params)
    # Same Gaussians, same order: each kept one moved by far less than the scene's size.
    assert float((refined.means - sm.params.means[keep]).norm(dim=1).max()) < 0.1
