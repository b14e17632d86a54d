"""3-D global registration of local maps (registration.global_registration) and verification by rendering
(slam.dense.loops.render_check), on the analytic box room: two views 50 degrees and 1.4 m apart, which share
3-D structure but little of one image."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration import synthetic as S
from swarmsplat.registration.global_registration import (GlobalResult, global_register, kiss_matcher_available,
                                                         prepare_cloud, refine, resolve_method)

CAM = S.default_camera(160, 120)
T_A = S.pose((0.0, -0.2, -1.0), (0.0, 0.0, 0.0))
T_B = S.pose((1.0, -0.2, 0.0), (0.0, -50.0, 0.0))


def _cloud(T_w_c):
    _, d = S.render(CAM, T_w_c)
    return CAM.backproject(d)[d > 0]


def _error(T, T_true):
    E = se3.inverse(T_true) @ T
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(se3.rotation_angle(E[:3, :3])))


def test_prepare_cloud_checks_and_refuses_too_little():
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        prepare_cloud(np.zeros((10, 2)), 0.05)
    with pytest.raises(InputError, match="voxel"):
        prepare_cloud(np.zeros((10, 3)), 0.0)
    assert prepare_cloud(np.random.default_rng(0).normal(size=(50, 3)), 0.05, min_points=200) is None
    c = prepare_cloud(_cloud(T_A), 0.08)
    assert len(c) > 1000 and c.normals.shape == c.points.shape
    assert np.allclose(np.linalg.norm(c.normals, axis=1), 1.0, atol=1e-6)


def test_unknown_method_is_one_line():
    with pytest.raises(InputError, match="expected one of"):
        resolve_method("teaser")


@pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher wheel not installed (x86-64 only)")
def test_kiss_matcher_registers_a_wide_pair():
    A, B = prepare_cloud(_cloud(T_A), 0.08), prepare_cloud(_cloud(T_B), 0.08)
    r = refine(B, A, global_register(B, A, method="kiss-matcher"))
    assert r.found and r.method == "kiss-matcher"
    dt, dr = _error(r.T_target_source, se3.inverse(T_A) @ T_B)
    assert dt < 0.03 and dr < 1.0, (dt, dr)
    assert r.fitness > 0.3 and r.inlier_rmse < 0.04
    assert r.information.shape == (6, 6) and r.n_correspondences > 100


def test_refine_from_the_truth_keeps_it_and_scores_overlap():
    """From the true pose, ICP stays there; from a pose 90 degrees off, the fitness is that of a wrong fit."""
    A, B = prepare_cloud(_cloud(T_A), 0.08), prepare_cloud(_cloud(T_B), 0.08)
    T_true = se3.inverse(T_A) @ T_B
    good = refine(B, A, GlobalResult(T_true, True, "given"))
    dt, dr = _error(good.T_target_source, T_true)
    assert dt < 0.02 and dr < 0.5
    bad = refine(B, A, GlobalResult(T_true @ S.pose((0, 0, 0), (0, 90, 0)), True, "given"))
    assert _error(bad.T_target_source, T_true)[1] > 20


def test_different_voxels_are_refused():
    A, B = prepare_cloud(_cloud(T_A), 0.08), prepare_cloud(_cloud(T_B), 0.1)
    with pytest.raises(InputError, match="different voxels"):
        global_register(B, A)


# ---- verification by rendering -------------------------------------------------------------------------------


def _gaussians_of_view(T_w_c, stride=1):
    """Gaussians on view T_w_c's surfaces (world frame), one per pixel: a stand-in for a mapped submap."""
    from swarmsplat.slam.dense.gaussian_map import GaussianParams

    c, d = S.render(CAM, T_w_c)
    ok = d > 0
    P = CAM.backproject(d)[ok][::stride]
    P = P @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    z = d[ok][::stride]
    rgb = c[ok][::stride] / 255.0
    return GaussianParams.from_points(torch.as_tensor(P, dtype=torch.float32), torch.as_tensor(rgb, dtype=torch.float32),
                                      torch.as_tensor(1.5 * z / CAM.fx, dtype=torch.float32), opacity=0.95)


class _View:
    def __init__(self, T_w_c):
        self.color, self.depth = S.render(CAM, T_w_c)
        self.camera = CAM


def test_render_check_tells_a_right_pose_from_a_wrong_one():
    from swarmsplat.slam.dense.loops.render_check import RenderGate, score_view

    T_mid = S.pose((0.5, -0.2, -0.5), (0.0, -25.0, 0.0))  # a query between the two mapped views
    params = _gaussians_of_view(T_A)
    params = params.concat([params, _gaussians_of_view(T_B)])
    view = _View(T_mid)
    gate = RenderGate()
    right = score_view(params, T_mid, view)
    assert right.covisible > 0.5 and right.agree > 0.6 and right.violate < 0.1 and right.photometric < 0.08
    assert gate.verdict(right) == ""
    # 40 cm forward: the map now lies in front of / behind what the camera saw.
    wrong = score_view(params, T_mid @ S.pose((0.0, 0.0, 0.4)), view)
    assert gate.verdict(wrong) != ""
    assert wrong.agree < right.agree
    # 60 degrees off: the map seen from there contradicts the query's depth.
    turned = score_view(params, T_mid @ S.pose((0.0, 0.0, 0.0), (0.0, 60.0, 0.0)), view)
    assert gate.verdict(turned) != ""


def test_render_check_of_an_empty_map_or_view_rejects_with_a_reason():
    from swarmsplat.slam.dense.gaussian_map import GaussianParams
    from swarmsplat.slam.dense.loops.render_check import RenderGate, score_view

    view = _View(T_A)
    s = score_view(GaussianParams.empty(), T_A, view)
    assert s.covisible == 0.0 and "covers 0 %" in RenderGate().verdict(s)
    view.depth = np.zeros_like(view.depth)
    s = score_view(_gaussians_of_view(T_A, stride=4), T_A, view)
    assert s.pixels == 0 and RenderGate().verdict(s) != ""


def test_render_check_forgives_exposure_but_not_a_different_picture():
    from swarmsplat.slam.dense.loops.render_check import score_view

    params = _gaussians_of_view(T_A)
    view = _View(T_A)
    base = score_view(params, T_A, view).photometric
    view.color = np.clip(view.color.astype(np.float64) * 0.7 + 20, 0, 255).astype(np.uint8)  # darker, lifted
    assert score_view(params, T_A, view).photometric < base + 0.02
    view.color = np.random.default_rng(0).integers(0, 256, view.color.shape, dtype=np.uint8)
    assert score_view(params, T_A, view).photometric > 0.15
