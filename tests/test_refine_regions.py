"""The merged-map refinement region by region (slam.dense.mapping.refine_regions, map_refine.region_gaussians): the
spatial split, one region being refine_map itself bit for bit, the hidden-copy cull a view at a time, and on
generated rooms: each region is fitted over the keyframes that see it (two rooms: its own; one room split in two:
all of them, and as well as the whole map at once), and each keyframe's pose is refined in one region."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat.kernels import use_reference
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.config import ExposureConfig, MappingConfig, MapRefineConfig
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.mapping.refine_merged import RefineView, contributions, iteration_budget, refine_map
from swarmsplat.slam.dense.mapping.refine_regions import refine_by_region, split_regions, whole_map_keep
from swarmsplat.slam.dense.render import render, viewmat_from_pose

CAM = PinholeCamera(40.0, 40.0, 15.5, 11.5, 32, 24)
ROOMS = (0.0, 20.0)  # x of each room's centre: far enough apart that no view of one sees the other


def test_split_regions_partitions_the_points_into_bounded_spatial_groups():
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal([x, 0, 0], 0.5, (50, 3)) for x in (0.0, 10.0, 20.0)])
    pts = pts[rng.permutation(len(pts))]
    for max_size in (1, 7, 40, 64, 149):
        regions = split_regions(pts, max_size)
        assert len(regions) == -(-len(pts) // max_size)
        assert all(len(r) <= max_size for r in regions)
        assert all(np.all(np.diff(r) > 0) for r in regions)  # ascending
        assert np.array_equal(np.sort(np.concatenate(regions)), np.arange(len(pts)))
    regions = split_regions(pts, 50)  # three clusters of 50: one region each
    assert sorted(int(np.round(np.median(pts[r][:, 0]))) for r in regions) == [0, 10, 20]
    assert [len(r) for r in split_regions(pts, 0)] == [150]
    assert [len(r) for r in split_regions(pts, 150)] == [150]
    assert [len(r) for r in split_regions(np.zeros((0, 3)), 4)] == [0]


def _pose(x: float, y: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, 0.0]
    return T


def _scene(hidden: bool = True, rooms=ROOMS):
    """In each room a wall of Gaussians at z = 2 in front of the room's four cameras (looking down +z) and
    (hidden) a copy of part of it at z = 2.6 behind the opaque wall. The targets are the map rendered with other
    colours; two rooms' keyframes come interleaved, as from a mission that goes back and forth."""
    g = torch.Generator().manual_seed(0)
    pts, n = [], 60
    for x in rooms:
        pts.append(torch.cat([torch.rand(n, 2, generator=g) * torch.tensor([1.4, 1.0]) - torch.tensor([0.7 - x, 0.5]),
                              2.0 + 0.05 * torch.rand(n, 1, generator=g)], 1))
        if hidden:
            pts.append(torch.cat([torch.rand(10, 2, generator=g) * 0.4 - torch.tensor([0.2 - x, 0.2]),
                                  torch.full((10, 1), 2.6)], 1))
    pts = torch.cat(pts)
    truth = GaussianParams.from_points(pts, torch.rand(len(pts), 3, generator=g), torch.full((len(pts),), 0.08),
                                       opacity=0.95)
    start = GaussianParams(*(t.clone() for t in truth.tensors()))
    start.colors = torch.rand(len(pts), 3, generator=g)
    views = []
    with use_reference():
        for x in rooms:
            for dx, dy in [(-0.1, -0.05), (0.1, -0.05), (-0.1, 0.05), (0.1, 0.05)]:
                vm = viewmat_from_pose(_pose(x + dx, dy))
                out = render(truth, vm, CAM)
                views.append(RefineView(vm, out.color.detach(), out.depth.detach(), CAM))
    if len(rooms) == 2:
        views = [views[i] for i in [0, 4, 1, 5, 2, 6, 3, 7]]
    return start, views


def _room(params: GaussianParams) -> torch.Tensor:
    return params.means[:, 0] > ROOMS[1] / 2  # True: the second room


def _error(params: GaussianParams, views) -> float:
    """Mean absolute colour error of `params` rendered against the views' targets."""
    with use_reference():
        return float(np.mean([float((render(params, v.viewmat, CAM).color - v.color).abs().mean()) for v in views]))


def test_one_region_is_refine_map_bit_for_bit():
    p, views = _scene()
    for k in (0, len(p), 10_000):
        cfg = MapRefineConfig(iterations_per_keyframe=3, region_gaussians=k, refine_poses=True)
        with use_reference():
            a, keep_a, st_a = refine_map(p, views, cfg, MappingConfig())
            b, keep_b, st_b, info = refine_by_region(p, views, cfg, MappingConfig())
        assert info["regions"] == 1
        assert torch.equal(keep_a, keep_b)
        assert all(torch.equal(x, y) for x, y in zip(a.tensors(), b.tensors()))
        assert st_a.loss_last == st_b.loss_last
        assert all(torch.equal(x, y) for x, y in zip(st_a.viewmats, st_b.viewmats))


def test_a_map_within_the_bound_once_its_hidden_copies_are_gone_is_refined_whole():
    """Regions are for what stays after the hidden-copy cull: a map above the bound only with its hidden copies is
    one region, refine_map bit for bit (the copies dropped the same way, the same steps)."""
    p, views = _scene()
    cfg = MapRefineConfig(iterations_per_keyframe=3, min_contribution=0.2)
    with use_reference():
        kept = int(whole_map_keep(p, views, cfg.min_contribution, cfg.view_margin).sum())
        assert kept < len(p)
        cfg = cfg.model_copy(update={"region_gaussians": kept})
        a, keep_a, st_a = refine_map(p, views, cfg, MappingConfig())
        b, keep_b, st_b, info = refine_by_region(p, views, cfg, MappingConfig())
        _, _, _, split = refine_by_region(p, views, cfg.model_copy(update={"region_gaussians": kept - 1}),
                                          MappingConfig())
    assert info == {"regions": 1, "region_gaussians_max": kept, "region_keyframes_max": len(views)}
    assert split["regions"] == 2  # one Gaussian more than the bound: regions
    assert torch.equal(keep_a, keep_b)
    assert all(torch.equal(x, y) for x, y in zip(a.tensors(), b.tensors()))
    assert (st_b.gaussians, st_b.iterations, st_b.loss_last) == (st_a.gaussians, st_a.iterations, st_a.loss_last)


def test_the_hidden_copy_cull_a_view_at_a_time_is_the_whole_maps():
    p, views = _scene()
    with use_reference():
        whole = contributions(p, views) >= 0.2
        assert torch.equal(whole_map_keep(p, views, 0.2, 0.15), whole)
    assert 0 < int((~whole).sum()) < len(p)  # the hidden copies are dropped, the walls kept


def test_rooms_are_refined_over_their_own_keyframes():
    p, views = _scene()
    cfg = MapRefineConfig(iterations_per_keyframe=6, region_gaussians=len(p) // 2, min_contribution=0.2)
    with use_reference():
        whole = contributions(p, views) >= cfg.min_contribution
        refined, keep, st, info = refine_by_region(p, views, cfg, MappingConfig())
    room = _room(p)
    assert info == {"regions": 2, "region_keyframes_max": 4,
                    "region_gaussians_max": max(int((whole & room).sum()), int((whole & ~room).sum()))}
    assert torch.equal(keep, whole)
    assert st.iterations == iteration_budget(cfg, len(views))  # each keyframe is in one region: the same steps
    assert st.loss_last < 0.7 * st.loss_first
    start = p.select(keep)
    assert ((refined.colors - start.colors).abs().sum(dim=1) > 0).all()  # every kept Gaussian was optimised
    assert _error(refined, views) < 0.6 * _error(start, views)


@pytest.mark.parametrize("n_regions", [2, 12])
def test_regions_of_one_room_fit_as_the_whole_map_does(n_regions):
    """Every keyframe sees all of one wall: each region of it (halves; or twelve strips, each a small share of
    what a view sees) is fitted over all of them, drawn with the rest, and the result is as good as refining the
    wall at once."""
    p, views = _scene(hidden=False, rooms=ROOMS[:1])
    cfg = MapRefineConfig(iterations_per_keyframe=8, min_contribution=0.0)
    with use_reference():
        whole, _, _ = refine_map(p, views, cfg, MappingConfig())
        parts, _, st, info = refine_by_region(
            p, views, cfg.model_copy(update={"region_gaussians": -(-len(p) // n_regions)}), MappingConfig())
    assert info["regions"] == n_regions and info["region_keyframes_max"] == len(views)
    assert st.iterations == n_regions * iteration_budget(cfg, len(views))  # every keyframe visited in each region
    e0, e_whole, e_parts = _error(p, views), _error(whole, views), _error(parts, views)
    assert e_whole < 0.6 * e0
    assert e_parts < 1.15 * e_whole


def test_region_pose_refinement_moves_each_keyframe_in_its_home_region():
    p, views = _scene(hidden=False)
    cfg = MapRefineConfig(iterations_per_keyframe=4, region_gaussians=len(p) // 2, refine_poses=True,
                          min_contribution=0.0)
    with use_reference():
        _, _, st, info = refine_by_region(p, views, cfg, MappingConfig(), fixed_views={1})
    assert info["regions"] == 2
    assert len(st.viewmats) == len(views) and st.pose_moves.shape == (len(views), 2)
    for j, v in enumerate(views):
        assert torch.equal(st.viewmats[j], v.viewmat) == (j == 1), j  # the gauge held, every other one moved
    assert st.pose_moves[1].tolist() == [0.0, 0.0]
    assert (st.pose_moves[[0, 2, 3, 4, 5, 6, 7]].sum(axis=1) > 0).all()


def test_region_gaussians_is_validated():
    from swarmsplat.kernels.errors import InputError

    with pytest.raises((InputError, ValueError)):
        MapRefineConfig(region_gaussians=-1)


def test_visibility_is_the_projection_of_each_centre_into_the_grown_image():
    """Visibility.indices (half-spaces in the map frame) against projecting every centre: the same set, apart from
    centres within float32 rounding of the image's grown edge or the near plane; a view's pose turned and moved."""
    from swarmsplat.slam.dense.mapping.refine_merged import Visibility
    from swarmsplat.slam.dense.render import NEAR

    g = torch.Generator().manual_seed(3)
    means = torch.rand(200_000, 3, generator=g) * 8.0 - 4.0
    cam = PinholeCamera(fx=250.0, fy=240.0, cx=161.0, cy=104.0, width=320, height=213)
    angle = 0.7
    T = np.eye(4)
    T[:3, :3] = [[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]
    T[:3, 3] = [0.3, -0.2, -1.5]
    view = RefineView(viewmat_from_pose(T), None, None, cam)
    seen = Visibility(means)
    for margin in (0.0, 0.15):
        got = set(seen.indices(view, margin).tolist())
        vm = view.viewmat.to(torch.float64)
        pc = means.double() @ vm[:3, :3].T + vm[:3, 3]
        z = pc[:, 2]
        u = cam.fx * pc[:, 0] / z.clamp_min(NEAR) + cam.cx
        v = cam.fy * pc[:, 1] / z.clamp_min(NEAR) + cam.cy
        mu, mv = margin * cam.width, margin * cam.height
        edge = torch.stack([u + mu, cam.width + mu - u, v + mv, cam.height + mv - v]).min(dim=0).values
        want = set(torch.nonzero((z > NEAR) & (edge > 0)).squeeze(1).tolist())
        near_edge = set(torch.nonzero(((edge.abs() < 1e-3) | ((z - NEAR).abs() < 1e-5))).squeeze(1).tolist())
        assert 1000 < len(want) < len(means) // 2  # the view sees a part of the points, not none or all
        assert (got ^ want) <= near_edge


@pytest.mark.parametrize("with_exposure", [False, True])
def test_auto_pose_refinement_follows_the_cameras_exposure_model(with_exposure):
    """map_refine.refine_poses "auto" (the default): the keyframes' poses are refined where they carry an exposure
    (the model on: a real camera), and stay where they are otherwise, whole map and by region alike."""
    from swarmsplat.slam.dense.mapping.exposure import identity

    p, views = _scene(hidden=False)
    if with_exposure:
        views = [v.at(exposure=identity()) for v in views]
        for v in views:
            v.exposure_prior = identity()
    assert MapRefineConfig().refine_poses == "auto"
    for k in (0, len(p) // 2):
        cfg = MapRefineConfig(iterations_per_keyframe=2, region_gaussians=k, min_contribution=0.0)
        with use_reference():
            _, _, st, _ = refine_by_region(p, views, cfg, MappingConfig(), exposure=ExposureConfig())
        assert (st.viewmats is not None) == with_exposure
        if with_exposure:
            assert (st.pose_moves[1:].sum(axis=1) > 0).all()
