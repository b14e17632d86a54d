"""The photometric model of a real camera (slam.dense.mapping.exposure): the affine transform, its robust fit,
mapping with it on an analytic scene whose second view is darker, and a black frame that must not corrupt the map."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.mapping import exposure
from swarmsplat.slam.dense.mapping.mapper import MapKeyframe, Mapper
from swarmsplat.slam.dense.render import render, viewmat_from_pose
from swarmsplat.slam.metrics import psnr
from swarmsplat.slam.metrics.views import exposure_record, held_out_exposure

import slam_scene

E = np.array([np.log(0.6), np.log(0.7), np.log(0.55), 0.0, 0.0, 0.0])  # a darker, bluer camera
E_OFFSET = np.array([np.log(0.6), np.log(0.7), np.log(0.55), 0.03, 0.01, 0.05])  # ... with a black level


@pytest.fixture(scope="module")
def warp_cpu():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    kernels.use("warp", "cpu")
    yield
    torch.set_num_threads(n)


def test_apply_and_unapply_are_inverse_and_keep_empty_pixels_black():
    rng = np.random.default_rng(0)
    c = rng.uniform(0.1, 0.9, (5, 7, 3)).astype(np.float32)
    seen = exposure.apply(torch.as_tensor(c), torch.ones(5, 7), E_OFFSET).numpy()
    assert np.allclose(seen, c * np.exp(E_OFFSET[:3]) + E_OFFSET[3:], atol=1e-6)
    assert np.allclose(exposure.unapply(seen, E_OFFSET), c, atol=1e-5)
    assert torch.equal(exposure.apply(torch.as_tensor(c), torch.ones(5, 7), None), torch.as_tensor(c))
    assert torch.equal(exposure.apply(torch.zeros(2, 2, 3), torch.zeros(2, 2), E_OFFSET), torch.zeros(2, 2, 3))
    assert np.allclose(exposure.apply(torch.as_tensor(c), torch.ones(5, 7), exposure.identity()).numpy(), c)


def _scene(width=96, height=72):
    cam = slam_scene.camera(width, height)
    color, depth = slam_scene.render(np.eye(4), cam)
    return cam, color.astype(np.float64) / 255.0, depth


def test_fit_recovers_an_affine_camera_despite_outliers():
    cam, c, depth = _scene()
    rng = np.random.default_rng(1)
    image = np.clip(c * np.exp(E[:3]) + E[3:] + rng.normal(0, 0.005, c.shape), 0, 1)
    bad = rng.random(depth.shape) < 0.05  # highlights and moving things: 5 % of the pixels far off
    image[bad] = rng.uniform(0, 1, (int(bad.sum()), 3))
    f = exposure.fit(c, np.ones_like(depth), depth, image, depth, min_pixels=100)
    assert f is not None
    assert np.allclose(f.exposure, E, atol=0.02), f.exposure
    assert f.rmse_after < 0.3 * f.rmse_before
    # a black level is left to the optimisation: the gains alone still explain most of the difference
    image2 = np.clip(c * np.exp(E_OFFSET[:3]) + E_OFFSET[3:], 0, 1)
    f2 = exposure.fit(c, np.ones_like(depth), depth, image2, depth, min_pixels=100)
    assert f2 is not None and (f2.exposure[3:] == 0).all() and f2.rmse_after < 0.5 * f2.rmse_before
    # depth that disagrees with the render is not a surface both saw: no pixels, no fit
    assert exposure.fit(c, np.ones_like(depth), depth + 1.0, image, depth, min_pixels=100) is None
    # nor a black frame
    assert exposure.fit(c, np.ones_like(depth), depth, np.zeros_like(c), depth, min_pixels=100) is None


def test_an_implausible_step_is_an_outlier():
    prev = exposure.identity()
    assert not exposure.is_outlier(np.array([0.3, 0.2, 0.25, 0.02, 0, 0]), prev, 2.5)
    assert exposure.is_outlier(np.array([np.log(0.2), 0, 0, 0, 0, 0]), prev, 2.5)
    assert exposure.is_outlier(np.array([0, 0, 0, 0.5, 0, 0]), prev, 2.5)


def test_held_out_frames_take_the_exposure_between_their_keyframes():
    class K:
        def __init__(self, i, e):
            self.frame_index, self.exposure, self.exposure_outlier = i, np.full(6, e), False

    kfs = [K(10, 0.0), K(20, 1.0)]
    assert np.allclose(held_out_exposure(kfs, 15), 0.5)
    assert np.allclose(held_out_exposure(kfs, 0), 0.0) and np.allclose(held_out_exposure(kfs, 99), 1.0)
    assert held_out_exposure([], 3) is None
    rec = exposure_record(kfs)
    assert rec["keyframes"] == 2 and rec["outlier_keyframes"] == 0 and "evaluation" in rec


def _map_two_views(darker_exposure, cfg, iterations=60):
    """One submap mapped from the analytic room at two nearby poses; the second image seen by a darker camera.
    Returns (submap params, [(pose, clean image tensor, image as captured, exposure the mapper ended with)])."""
    cam = slam_scene.camera(64, 48)
    poses = [np.eye(4), se3.exp(np.array([0.0, 0.05, 0.0, 0.06, 0.0, 0.0]))]
    views = []
    for i, T in enumerate(poses):
        color, depth = slam_scene.render(T, cam)
        clean = color.astype(np.float32) / 255.0
        seen = clean if i == 0 else np.clip(clean * np.exp(E[:3]) + E[3:], 0, 1)
        views.append((T, clean, make_rgbd((seen * 255).round().astype(np.uint8), depth, cam, min_depth=0.1,
                                          max_depth=10.0)))
    gm = GaussianMap()
    sm = gm.new_submap(np.eye(4))
    mapper = Mapper(cfg.mapping, cfg.exposure if darker_exposure is not None else None)
    first = MapKeyframe(poses[0], views[0][2], exposure.identity() if darker_exposure is not None else None,
                        exposure.identity() if darker_exposure is not None else None, exposure_fixed=True)
    mapper.map(gm, sm, [first], 60)
    e2 = None
    if darker_exposure is not None:  # what the agent does at a new keyframe: fit against the map's render
        with torch.no_grad():
            out = render(sm.params, viewmat_from_pose(poses[1]), cam)
        f2 = views[1][2]
        fitted = exposure.fit(out.color.clamp(0, 1).numpy(), out.alpha.numpy(), out.depth_normalised.numpy(),
                              f2.color / 255.0, f2.depth, min_pixels=200)
        assert fitted is not None
        e2 = fitted.exposure
    second = MapKeyframe(poses[1], views[1][2], e2, None if e2 is None else e2.copy())
    mapper.map(gm, sm, [first, second], iterations)
    return sm.params, [(T, torch.as_tensor(clean), f.color_tensor(), k.exposure)
                       for (T, clean, f), k in zip(views, [first, second])]


def test_mapping_with_the_model_keeps_the_map_in_the_first_cameras_colours(warp_cpu):
    cfg = SlamConfig().override({"exposure": {"enabled": True}})
    with_model, views = _map_two_views(True, cfg)
    without, _ = _map_two_views(None, cfg)
    e2 = views[1][3]
    assert np.allclose(np.exp(e2[:3]), np.exp(E[:3]), atol=0.08), e2  # the darker camera is recognised

    def scores(params, T, target, e=None):
        with torch.no_grad():
            o = render(params, viewmat_from_pose(T), slam_scene.camera(64, 48))
            c = exposure.apply(o.color, o.alpha, e).clamp(0, 1)
        return psnr(c.permute(2, 0, 1), target.permute(2, 0, 1))

    # The first view, in the map's own colours: the model keeps it; without the model the darker second image
    # pulls the shared surfaces' colours toward it.
    T0, clean0 = views[0][0], views[0][1]
    assert scores(with_model, T0, clean0) > scores(without, T0, clean0) + 1.0
    # The second view as its camera saw it: the model renders it darker, as captured.
    T1, _, seen1, _ = views[1]
    assert scores(with_model, T1, seen1, e2) > scores(without, T1, seen1) + 1.0


def test_the_map_gauge_moves_to_the_median_keyframe_and_keeps_every_exposed_render(warp_cpu):
    from types import SimpleNamespace

    params, views = _map_two_views(True, SlamConfig().override({"exposure": {"enabled": True}}))
    e2 = views[1][3]
    cam = slam_scene.camera(64, 48)
    # three keyframes drifting darker (the first camera, the second, one darker still) and an outlier, whose
    # gain takes no part in the median
    kf = lambda e, outlier=False: SimpleNamespace(exposure=e.copy(), exposure_prior=e.copy(),  # noqa: E731
                                                  exposure_outlier=outlier)
    e3 = e2.copy()
    e3[:3] *= 2
    wild = exposure.identity()
    wild[:3] = 3.0
    kfs = [kf(exposure.identity()), kf(e2), kf(e3), kf(wild, True)]
    seen = [(views[0][0], kfs[0]), (views[1][0], kfs[1]), (views[1][0], kfs[2]), (views[1][0], kfs[3])]

    def renders(own=False):
        with torch.no_grad():
            out = [render(params, viewmat_from_pose(T), cam) for T, _ in seen]
            return [o.color.clamp(0, 1) if own else exposure.apply(o.color, o.alpha, k.exposure).clamp(0, 1)
                    for o, (_, k) in zip(out, seen)]

    before, own_before = renders(), renders(own=True)
    m = exposure.median_gauge(params.colors, kfs)
    np.testing.assert_allclose(m, e2[:3], atol=1e-12)  # the second keyframe is the median one
    np.testing.assert_allclose(kfs[1].exposure[:3], 0.0, atol=1e-12)  # ... now the map's own gauge
    for k, e in zip(kfs, [exposure.identity(), e2, e3, wild]):  # every gain and anchor moves by -m, offsets stay
        np.testing.assert_allclose(k.exposure[:3], e[:3] - m, atol=1e-12)
        np.testing.assert_allclose(k.exposure_prior, k.exposure, atol=0)
        np.testing.assert_allclose(k.exposure[3:], e[3:], atol=0)
    for a, b in zip(renders(), before):  # every keyframe's exposed render is unchanged (the map only darkened)
        torch.testing.assert_close(a, b, atol=2e-5, rtol=0)
    # the map's own colours now render the darker camera's view as that camera saw it, not as the first did
    seen1 = views[1][2]
    score = lambda c: psnr(c.permute(2, 0, 1), seen1.permute(2, 0, 1))  # noqa: E731
    assert score(renders(own=True)[1]) > score(own_before[1]) + 1.0
    assert exposure.median_gauge(params.colors, [kf(exposure.identity(), True)]) is None


def test_the_map_gauge_brightens_only_as_far_as_few_colours_clip():
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    colors = torch.as_tensor(rng.uniform(0.0, 0.8, (2000, 3)), dtype=torch.float32)
    e = exposure.identity()
    e[:3] = np.log([1.5, 1.1, 2.0])  # the keyframes see the map brighter: the median gauge would clip many colours
    kfs = [SimpleNamespace(exposure=e.copy(), exposure_prior=e.copy(), exposure_outlier=False) for _ in range(3)]
    c = colors.clone()
    m = exposure.median_gauge(c, kfs, clip_fraction=0.01)
    passed = (c > 1.0 + 1e-6).float().mean(dim=0).numpy()
    assert np.all(passed <= 0.01 + 1e-3), passed
    assert m[1] == pytest.approx(np.log(1.1))  # green: the median clips nothing, taken whole
    assert m[0] < np.log(1.5) and m[2] < np.log(2.0)  # red, blue: capped
    np.testing.assert_allclose(c.numpy(), (colors * torch.as_tensor(np.exp(m), dtype=torch.float32)).numpy(),
                               rtol=1e-6)
    np.testing.assert_allclose(kfs[0].exposure[:3], e[:3] - m, atol=1e-12)


def test_a_black_keyframe_is_an_outlier_and_leaves_the_map_alone(warp_cpu):
    from swarmsplat.slam.dense.agent import Agent

    cam = slam_scene.camera(64, 48)
    cfg = SlamConfig().override({"image": {"max_width": 64}, "keyframes": {"every": 1}, "exposure": {"enabled": True},
                                 "loop_closure": {"enabled": False}, "map_refine": {"single_agent": False}})
    path = [se3.exp(np.array([0.0, 0.01 * i, 0.0, 0.02 * i, 0.0, 0.0])) for i in range(5)]

    def run(black: bool):
        ag = Agent(cam, cfg)
        for i, T in enumerate(path):
            color, depth = slam_scene.render(T, cam)
            if black and i == 3:
                color = np.zeros_like(color)
            ag.step(i, 0.1 * i, color, depth)
        return ag

    clean, dark = run(False), run(True)
    assert exposure_record(dark.keyframes)["outlier_keyframes"] == 1
    assert exposure_record(clean.keyframes)["outlier_keyframes"] == 0
    black = dark.keyframes[3]  # keeps the exposure it inherited, not the black frame's
    assert black.exposure_outlier and np.array_equal(black.exposure, black.exposure_prior)
    assert np.abs(black.exposure[:3]).max() < 0.1
    color, _ = slam_scene.render(path[2], cam)
    target = torch.as_tensor(color).float().permute(2, 0, 1) / 255.0

    def score(ag):
        c, _ = ag.render_keyframe(ag.keyframes[2], cam)
        return psnr(c.permute(2, 0, 1), target)

    assert score(dark) > score(clean) - 1.5  # the black frame did not paint the map black


def test_fits_against_several_submaps_combine_by_their_pixels():
    a = exposure.Fit(np.array([0.0, 0, 0, 0, 0, 0]), 300, 0.2, 0.1)
    b = exposure.Fit(np.array([0.4, 0.4, 0.4, 0, 0, 0]), 100, 0.3, 0.1)
    c = exposure.combine([a, b])
    assert np.allclose(c.exposure[:3], 0.1) and c.pixels == 400
    assert exposure.combine([]) is None and exposure.combine([b]).exposure[0] == pytest.approx(0.4)


def _walk(cfg, darker_from: int | None, n: int = 5):
    """An agent over the analytic scene, one keyframe per frame; frames from `darker_from` on are seen by a darker,
    bluer camera (E)."""
    from swarmsplat.slam.dense.agent import Agent

    cam = slam_scene.camera(64, 48)
    ag = Agent(cam, cfg)
    for i in range(n):
        T = se3.exp(np.array([0.0, 0.01 * i, 0.0, 0.02 * i, 0.0, 0.0]))
        color, depth = slam_scene.render(T, cam)
        if darker_from is not None and i >= darker_from:
            color = (np.clip(color / 255.0 * np.exp(E[:3]), 0, 1) * 255).round().astype(np.uint8)
        ag.step(i, 0.1 * i, color, depth)
    return ag


def _walk_cfg(enabled):
    return SlamConfig().override({"image": {"max_width": 64}, "keyframes": {"every": 1}, "exposure": {"enabled": enabled},
                                  "loop_closure": {"enabled": False}, "map_refine": {"single_agent": False}})


def test_auto_leaves_a_camera_of_constant_exposure_exactly_as_without_the_model(warp_cpu):
    auto, off = _walk(_walk_cfg("auto"), None), _walk(_walk_cfg(False), None)
    assert not auto.exposure_active and auto.exposure_from is None
    assert all(k.exposure is None for k in auto.keyframes)
    np.testing.assert_array_equal(auto.trajectory()[1], off.trajectory()[1])
    for a, b in zip(auto.gmap.merged().tensors(), off.gmap.merged().tensors()):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    assert exposure.display_gain(auto.keyframes) is None
    assert torch.equal(auto.display_map().colors, auto.gmap.merged().colors.clamp(0, 1))  # map.ply: the map as rendered


def test_auto_switches_the_model_on_when_the_camera_darkens(warp_cpu):
    ag = _walk(_walk_cfg("auto"), darker_from=2)
    assert ag.exposure_active and ag.exposure_from == 2
    for k in ag.keyframes[:2]:  # before the change: anchored at the identity (the map's colours are theirs)
        np.testing.assert_array_equal(k.exposure_prior, exposure.identity())
        assert np.abs(k.exposure).max() < 0.02, k.exposure  # mapping has optimised them a little since
    for k in ag.keyframes[2:]:  # the darker camera is recognised from the keyframe that saw it first
        assert np.allclose(np.exp(k.exposure[:3]), np.exp(E[:3]), atol=0.08), k.exposure
    # a camera that only ever saw the scene darker than the map by less than the threshold keeps the model off
    cfg = _walk_cfg("auto").override({"exposure": {"auto_threshold": 1.0}})
    assert not _walk(cfg, darker_from=2).exposure_active


def test_auto_reads_a_change_against_the_maps_own_colour_error(warp_cpu, monkeypatch):
    """A map that misses its keyframes' colours (here dimmed by 15 % after every mapping, as a real-time map mapped
    for a few iterations renders them) reads as a gain on the next keyframe of a camera whose exposure never
    changes. Auto measures that gain against the previous keyframe's fit to the same map: the model stays off, and
    a real change of the camera still switches it on at the keyframe that saw it first."""
    from swarmsplat.slam.dense.agent import Agent

    mapped = Agent._map

    def dimmed(self, kf, **kw):
        stats = mapped(self, kf, **kw)
        with torch.no_grad():
            self.gmap.submaps[kf.submap_id].params.colors.mul_(0.85)
        return stats

    monkeypatch.setattr(Agent, "_map", dimmed)
    assert not _walk(_walk_cfg("auto"), None).exposure_active
    changed = _walk(_walk_cfg("auto"), darker_from=2)
    assert changed.exposure_active and changed.exposure_from == 2
    monkeypatch.setattr(Agent, "_map_colour_bias", lambda self, kf: None)  # the check this test is about, left out
    assert _walk(_walk_cfg("auto"), None).exposure_active  # the dimmed map alone switches the model on


def test_the_written_map_holds_the_colours_a_typical_keyframe_saw(tmp_path):
    from types import SimpleNamespace

    from swarmsplat.slam.dense.gaussian_map import GaussianParams
    from swarmsplat.slam.dense.ply import load_ply, save_ply

    colors = torch.tensor([[0.2, 0.5, 0.9], [1.3, -0.1, 0.5]])  # the second: outside [0, 1], clamped as rendered
    params = GaussianParams.from_points(torch.zeros(2, 3), colors, torch.full((2,), 0.01), 0.5)
    e = lambda g, outlier=False: SimpleNamespace(exposure=np.array([*np.log(g), 0, 0, 0]),  # noqa: E731
                                                 exposure_outlier=outlier)
    kfs = [e([1.0, 1.0, 1.0]), e([1.5, 1.2, 0.8]), e([2.0, 1.4, 0.9]), e([9.0, 9.0, 9.0], True)]
    gain = exposure.display_gain(kfs)
    np.testing.assert_allclose(gain, [1.5, 1.2, 0.9])  # the median of the three that are not outliers
    shown = exposure.for_display(params, kfs)
    want = colors.clamp(0, 1) * torch.tensor([1.5, 1.2, 0.9])
    torch.testing.assert_close(shown.colors, want)
    torch.testing.assert_close(params.colors, colors)  # the map itself is left as it was
    save_ply(tmp_path / "map.ply", shown, max_color=None)
    torch.testing.assert_close(load_ply(tmp_path / "map.ply").colors, want)  # above 1 survives the file
    save_ply(tmp_path / "raw.ply", shown)  # by default as the rasteriser clamps each Gaussian
    torch.testing.assert_close(load_ply(tmp_path / "raw.ply").colors, want.clamp(0, 1))


def test_the_ros2_map_points_show_the_colours_map_ply_holds():
    from swarmsplat.slam.dense.gaussian_map import GaussianParams
    from swarmsplat.slam.run.ros2.feed import PointCache

    params = GaussianParams.from_points(torch.zeros(2, 3), torch.tensor([[0.2, 0.5, 0.9], [0.8, 0.1, 0.5]]),
                                        torch.full((2,), 0.01), 0.5)
    submap = type("S", (), {"params": params, "__len__": lambda self: 2})()
    cache = PointCache()
    _, raw = cache.world([(0, submap, np.eye(4), True)], 10)
    gain = np.array([1.5, 1.2, 0.9])
    _, shown = cache.world([(0, submap, np.eye(4), True)], 10, gain)
    np.testing.assert_array_equal(raw, np.rint(params.colors.numpy() * 255).astype(np.uint8))
    np.testing.assert_array_equal(shown, np.clip(np.rint(raw * gain.astype(np.float32)), 0, 255).astype(np.uint8))
    assert shown[1, 0] == 255 and shown[0, 2] < raw[0, 2]  # brighter red clips at white, bluer channel darkens
