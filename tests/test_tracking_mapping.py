"""Tracking, mapping and submap transforms on a tiny analytic scene (64x48, a few thousand Gaussians)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import RGBD, make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap, transform_params
from swarmsplat.slam.dense.mapping.mapper import MapKeyframe, Mapper
from swarmsplat.slam.dense.render import render, viewmat_from_pose
from swarmsplat.slam.dense.tracking.tracker import Tracker, model_view, refine_against_view, refine_pose

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
    """A submap fitted to one 64x48 view at the origin. Seeds at the pixel footprint (init_scale_factor 1, the
    default before the 320 px tuning): small Gaussians keep the float32 rounding flips in
    test_submap_transform_moves_its_renders_exactly at ~1e-3."""
    cam = slam_scene.camera(64, 48)
    cfg = SlamConfig().override({"mapping": {"seed_stride": 1, "init_scale_factor": 1.0}})
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
    # The paper's eq. 5 by Adam through the rasteriser's pose gradient (tracking.method adam). The frame is the
    # map's own render, normalised by alpha, so the loss normalises too.
    # Iterations: Adam moves at most ~lr (2 mm) per step, so after 50 steps it was still on its way (5.9 mm left
    # of 32 mm, against the 6 mm bound: an error set by how far the optimiser got, which any change in the map's
    # float32 fit moves). After 100 it sits at its floor (0.4-0.8 mm here with torch's AVX-512, AVX2 and scalar
    # kernels; 0.8 mm after 200), which the bounds below clear by > 7x on any CPU.
    tc = cfg.tracking.model_copy(update={"method": "adam", "refine_max_width": 64, "pyramid_levels": 1,
                                         "adam_iterations": 100, "normalise_by_alpha": True})
    T, iters, _ = refine_pose(sm.params, frame, T0, tc)
    err = lambda A: se3.inverse(T_true) @ A  # noqa: E731
    t0, t1 = np.linalg.norm(err(T0)[:3, 3]), np.linalg.norm(err(T)[:3, 3])
    r0, r1 = se3.rotation_angle(err(T0)[:3, :3]), se3.rotation_angle(err(T)[:3, :3])
    assert 0 < iters <= 100
    assert t1 < 0.2 * t0 and t1 < 0.006, (t0, t1)
    assert r1 < 0.1 * r0, (np.degrees(r0), np.degrees(r1))


def _pose_error(T_true, T):
    E = se3.inverse(T_true) @ T
    return np.linalg.norm(E[:3, 3]), np.degrees(se3.rotation_angle(E[:3, :3]))


@pytest.mark.parametrize("width", [64, 128])
def test_gauss_newton_refinement_against_a_model_view(warp_cpu, width):
    """The default refinement: a frame at T_true aligned to a view rendered 2 cm away (at T_view), from a start
    1.6 cm / 0.86 deg off T_true. An exact (ray-cast) view isolates the alignment and the pose composition."""
    cam = slam_scene.camera(width, width * 3 // 4)
    T_view = se3.exp(np.array([0.0, 0.02, 0.0, 0.0, 0.0, 0.0]))
    T_true = se3.exp(np.array([0.0, 0.03, 0.0, 0.02, 0.0, 0.01]))
    view, frame = _frame(T_view, cam), _frame(T_true, cam)
    tc = SlamConfig().tracking.model_copy(update={"refine_max_width": width})
    T0 = T_true @ se3.exp(np.array([0.01, -0.01, 0.005, 0.01, -0.008, 0.01]))
    T, iters, rmse = refine_against_view(frame, view, T_view, T0, tc)
    (t0, r0), (t1, r1) = _pose_error(T_true, T0), _pose_error(T_true, T)
    assert 0 < iters <= tc.iterations * tc.pyramid_levels and np.isfinite(rmse)
    assert t1 < 0.15 * t0 and r1 < 0.05 * r0, (t0, t1, r0, r1)
    # A correction beyond max_correction is refused: the input pose comes back untouched.
    T2, iters2, _ = refine_against_view(frame, view, T_view, T0, tc.model_copy(update={"max_correction": 0.002}))
    assert iters2 == 0 and np.array_equal(T2, T0)
    # A view that covers too little of the image is not used.
    empty = RGBD(view.color, np.zeros_like(view.depth), cam)
    assert refine_against_view(frame, empty, T_view, T0, tc)[1] == 0


def test_model_view_is_what_mapping_fits(mapped):
    """Composited colour and alpha-weighted depth (eq. 3 fits these, not depth / alpha), masked by alpha."""
    cam, cfg, _, sm, _ = mapped
    T = se3.exp(np.array([0.0, 0.02, 0.0, 0.01, 0.0, 0.0]))
    v = model_view(sm.params, T, cam, alpha_min=0.9)
    with torch.no_grad():
        out = render(sm.params, viewmat_from_pose(T), cam)
    keep = out.alpha.numpy() >= 0.9
    assert 0.5 < keep.mean() < 1.0 or keep.all()
    np.testing.assert_allclose(v.depth[keep], out.depth.numpy()[keep], rtol=1e-6)
    assert np.all(v.depth[~keep] == 0)
    assert np.abs(v.color.astype(int) - (out.color.clamp(0, 1).numpy() * 255).round()).max() <= 1


def test_tracker_renders_the_model_once_per_map_update(mapped, monkeypatch):
    import swarmsplat.slam.dense.tracking.tracker as tracker_mod

    cam, cfg, _, sm, _ = mapped
    calls = []
    real = tracker_mod.model_view
    monkeypatch.setattr(tracker_mod, "model_view", lambda *a, **k: calls.append(1) or real(*a, **k))
    tr = Tracker(cfg.tracking.model_copy(update={"refine": True, "refine_max_width": 64}))
    poses = [se3.exp(np.array([0.0, 0.004 * i, 0.0, 0.003 * i, 0.0, 0.0])) for i in range(4)]
    results = [tr.track(_frame(T, cam), sm.params) for T in poses[:3]]
    assert len(calls) == 1  # frame 0 starts the track; frames 1 and 2 share one render of the unchanged map
    tr.track(_frame(poses[3], cam), sm.params.detached())  # mapping replaced the params: render again
    assert len(calls) == 2
    for T_true, r in zip(poses[1:], results[1:]):
        assert _pose_error(T_true, r.T_local_cam)[0] < 0.01


def test_mapping_fills_a_hole(warp_cpu):
    """A depth hole left empty (seed_without_depth off) is seeded once a keyframe measures depth there."""
    cam = slam_scene.camera(64, 48)
    cfg = SlamConfig().override({"mapping": {"seed_stride": 1, "seed_without_depth": False}})
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


def test_pixels_without_depth_are_seeded_behind_what_was_measured(warp_cpu):
    """seed_without_depth (default): a large region without valid depth (a window, the sky) is seeded at the
    farthest valid depth around it and renders its colour; thin invalid lines and small holes are not seeded; off,
    the region stays empty."""
    from swarmsplat.slam.dense.mapping.mapper import fallback_depth

    cam = slam_scene.camera(64, 48)
    full = _frame(np.eye(4), cam)
    holed = RGBD(full.color, full.depth.copy(), cam)
    holed.depth[16:32, 24:44] = 0.0
    holed.depth[40, :] = 0.0  # a 1-px line (as along depth edges)
    holed.depth[4:8, 4:8] = 0.0  # a small hole (0.5 % of the image) in a measured surface
    z = fallback_depth(holed.depth, 0.01)
    assert (z[16:32, 24:44] > 0).all() and not z[40].any() and not z[holed.depth > 0].any()
    assert not z[4:8, 4:8].any() and fallback_depth(holed.depth, 0.004)[4:8, 4:8].all()
    ring = holed.depth[15:33, 23:45].copy()
    ring[1:-1, 1:-1] = 0
    assert z[16:32, 24:44].min() >= ring[ring > 0].min() - 1e-6  # never in front of what surrounds the hole
    assert np.allclose(z[18:30, 26:42], full.depth.max())  # inside it: the frame's farthest measured depth
    vm = viewmat_from_pose(np.eye(4))
    cover = {}
    for on in (True, False):
        cfg = SlamConfig().override({"mapping": {"seed_stride": 1, "seed_without_depth": on}})
        gm = GaussianMap()
        sm = gm.new_submap(np.eye(4))
        Mapper(cfg.mapping).map(gm, sm, [MapKeyframe(np.eye(4), holed)], 15)
        with torch.no_grad():
            out = render(sm.params, vm, cam)
        cover[on] = float(out.alpha[18:30, 26:42].mean())
        if on:
            err = (out.color[18:30, 26:42] - torch.as_tensor(full.color[18:30, 26:42] / 255.0)).abs().mean()
            assert err < 0.05, float(err)
    assert cover[True] > 0.9 and cover[False] < 0.3, cover


def test_submap_transform_moves_its_renders_exactly(mapped):
    cam, _, _, sm, _ = mapped
    T_view = se3.exp(np.array([0.02, -0.05, 0.01, 0.1, 0.0, -0.1]))  # camera in the submap's local frame
    D = se3.exp(np.array([0.3, -0.4, 0.2, 1.5, -0.7, 2.0]))  # move the whole submap
    moved = transform_params(sm.params, D)
    with torch.no_grad():
        a = render(sm.params, viewmat_from_pose(T_view), cam)
        b = render(moved, viewmat_from_pose(D @ T_view), cam)
    assert float(a.alpha.mean()) > 0.5
    # The two renders are equal up to float32 rounding of the moved means and view matrix (~1e-6 relative), except
    # at isolated pixels where the rounding crosses one of the rasteriser's discontinuities:
    #  - an alpha crossing the 1/255 cut-off (ALPHA_MIN) changes colour, alpha and depth by at most ALPHA_MIN
    #    times the value (colour <= 1, alpha <= 1, depth <= the farthest depth);
    #  - two Gaussians whose view depths lie within one float32 step (~1e-7 m at 2 m) swap places in the depth
    #    order: alpha is a product and does not change, depth changes by ~|z_i - z_j|, but colour changes by
    #    T a_i a_j |c_i - c_j|, which no small bound covers. Which pairs swap depends on the CPU's rounding (FMA
    #    contraction, the vector width of torch's and Warp's code): 0.0051 on one Zen 4 pixel, none on a Xeon.
    # So: alpha and depth within the cut-off bound everywhere; colour beyond it only where alpha is unchanged (a
    # swap, not a wrong transform); and a wrong transform would move far more than 1 % of the pixels.
    alpha_min = 1.0 / 255.0
    d_alpha = (a.alpha - b.alpha).abs()
    d_depth = (a.depth - b.depth).abs()
    d_color = (a.color - b.color).abs().amax(dim=-1)
    assert float(d_alpha.max()) <= 2 * alpha_min, float(d_alpha.max())
    assert float(d_depth.max()) <= 2 * alpha_min * float(a.depth.max()), float(d_depth.max())
    swapped = d_color > 2 * alpha_min
    assert bool((d_alpha[swapped] < 1e-4).all()), (float(d_color.max()), float(d_alpha[swapped].max()))
    for d in (d_alpha, d_depth, d_color):
        assert float((d > 1e-4).float().mean()) < 0.01 and float(d.mean()) < 1e-4, (float(d.max()), float(d.mean()))


def test_contributions_see_hidden_gaussians(warp_cpu):
    """A small Gaussian right behind an opaque larger one contributes (almost) nothing to the view; the front one
    a lot; one outside the view nothing."""
    from swarmsplat.slam.dense.gaussian_map import GaussianParams
    from swarmsplat.slam.dense.mapping.refine_merged import RefineView, contributions

    cam = slam_scene.camera(64, 48)
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.2], [5.0, 0.0, 2.0]])  # front, hidden behind it, out of view
    g = GaussianParams.from_points(pts, torch.full((3, 3), 0.5), torch.tensor([0.1, 0.03, 0.1]), opacity=0.99)
    view = RefineView(viewmat_from_pose(np.eye(4)), torch.zeros(48, 64, 3), torch.zeros(48, 64), cam)
    w = contributions(g, [view])
    assert w[0] > 10.0 and w[1] < 0.05 * w[0] and w[2] == 0.0


def test_refine_map_refines_a_misplaced_keyframe_pose(mapped):
    """refine_poses: a keyframe handed over 3 cm / 1.1 deg off the pose its image was taken from is moved most of
    the way back while the map is refined; the first view holds the gauge; refine_poses off returns no poses."""
    from swarmsplat.slam.dense.mapping.refine_merged import RefineView, refine_map

    cam, cfg, gm, sm, _ = mapped
    T1 = se3.exp(np.array([0.0, 0.05, 0.0, 0.04, 0.0, 0.0]))
    T1_off = T1 @ se3.exp(np.array([0.01, -0.015, 0.0, 0.02, -0.02, 0.01]))
    f0, f1 = _frame(np.eye(4), cam), _frame(T1, cam)
    views = [RefineView(viewmat_from_pose(np.eye(4)), f0.color_tensor(), f0.depth_tensor(), cam),
             RefineView(viewmat_from_pose(T1_off), f1.color_tensor(), f1.depth_tensor(), cam)]
    rc = cfg.map_refine.model_copy(update={"iterations_per_keyframe": 50, "min_contribution": 0.0,
                                           "refine_poses": True, "lr_pose_translation": 3e-3,
                                           "lr_pose_rotation": 3e-3})

    def error(viewmat):  # (translation m, rotation deg) of the camera against T1
        D = se3.inverse(T1) @ se3.inverse(viewmat.double().numpy())
        return float(np.linalg.norm(D[:3, 3])), float(np.degrees(se3.rotation_angle(D[:3, :3])))

    _, _, st = refine_map(sm.params, views, rc, cfg.mapping)
    t0, r0 = error(views[1].viewmat)
    t1, r1 = error(st.viewmats[1])
    assert t1 < 0.4 * t0 and r1 < 0.5 * r0, (t0, t1, r0, r1)
    assert torch.allclose(st.viewmats[0], views[0].viewmat, atol=1e-6) and st.pose_moves[0].tolist() == [0.0, 0.0]
    assert st.pose_moves[1, 1] > 0.5 * t0
    _, _, off = refine_map(sm.params, views, rc.model_copy(update={"refine_poses": False}), cfg.mapping)
    assert off.viewmats is None and off.pose_moves is None


@pytest.mark.parametrize("optimizer", ["selective", "adam"])
def test_refine_map_lowers_the_loss_and_keeps_order(mapped, optimizer):
    """Refining a submap over a second view it was never fitted to lowers the loss on that view; 0 steps is a
    no-op; the kept Gaussians come back in their input order. Both optimisers (selective Adam, torch's Adam)."""
    from swarmsplat.slam.dense.mapping.refine_merged import RefineView, iteration_budget, refine_map

    cam, cfg, gm, sm, _ = mapped
    T2 = se3.exp(np.array([0.0, 0.08, 0.0, 0.06, 0.0, 0.0]))
    f2 = _frame(T2, cam)
    views = [RefineView(viewmat_from_pose(T), f.color_tensor(), f.depth_tensor(), f.camera)
             for T, f in ((np.eye(4), _frame(np.eye(4), cam)), (T2, f2))]

    def loss(p):
        with torch.no_grad():
            out = render(p, views[1].viewmat, cam)
        return float((out.color - views[1].color).abs().mean())

    rc = cfg.map_refine.model_copy(update={"iterations_per_keyframe": 15, "optimizer": optimizer})
    assert iteration_budget(rc, 2) == 30
    assert iteration_budget(rc.model_copy(update={"max_iterations": 7}), 2) == 7
    same, keep0, st0 = refine_map(sm.params, views, rc, cfg.mapping, iterations=0)
    assert st0.iterations == 0 and bool(keep0.all()) and torch.equal(same.means, sm.params.means)
    refined, keep, st = refine_map(sm.params, views, rc, cfg.mapping)
    assert st.iterations == 30 and len(refined) == int(keep.sum()) and int(keep.sum()) > 0.5 * len(sm.params)
    assert loss(refined) < 0.9 * loss(sm.params)
    # Same Gaussians, same order: each kept one moved by far less than the scene's size.
    assert float((refined.means - sm.params.means[keep]).norm(dim=1).max()) < 0.1


def test_motion_prior_scales_the_last_step_to_the_frames_it_must_bridge(mapped):
    """A frame 3 frames after the previous one (two dropped in real time) starts three steps along; the step after
    it, one frame on, one step (a third of the step that spanned three frames); capped at MAX_GAP_RATIO."""
    from swarmsplat.slam.dense.tracking.tracker import MAX_GAP_RATIO

    cam, cfg, _, sm, _ = mapped
    xi = np.array([0.0, 0.004, 0.0, 0.003, 0.0, 0.0])  # [omega, v] per frame
    tr = Tracker(cfg.tracking.model_copy(update={"refine": True, "refine_max_width": 64}))
    poses = {i: se3.exp(xi * i) for i in (0, 1, 4, 5)}
    for i in (0, 1):
        tr.track(_frame(poses[i], cam), sm.params)
    assert tr.motion_prior(1) is tr._velocity  # the offline case: the last step as it is
    np.testing.assert_allclose(tr.motion_prior(3), se3.exp(3 * se3.log(tr._velocity)), atol=1e-12)
    np.testing.assert_allclose(se3.log(tr.motion_prior(100)), MAX_GAP_RATIO * se3.log(tr._velocity), atol=1e-12)
    r = tr.track(_frame(poses[4], cam), sm.params, gap=3)
    assert _pose_error(poses[4], r.T_local_cam)[0] < 0.01
    np.testing.assert_allclose(se3.log(tr.motion_prior(1)), se3.log(tr._velocity) / 3, atol=1e-12)


def test_the_agent_tells_the_tracker_how_many_frames_it_skipped():
    from swarmsplat.slam.dense.agent import Agent

    gaps = []

    class Stub:
        def track(self, frame, params, gap=1.0):
            gaps.append(gap)
            raise StopIteration

    a = Agent(slam_scene.camera(64, 48), SlamConfig())
    a.tracker = Stub()
    for last, index in ((None, 7), (3, 4), (3, 6)):
        a.poses = [] if last is None else [type("P", (), {"frame_index": last})()]
        with pytest.raises(StopIteration):
            a._track(None, index)
    assert gaps == [1, 1, 3]
