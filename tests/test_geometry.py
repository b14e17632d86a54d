import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

rng = np.random.default_rng(0)


def random_twists(n, scale=1.0):
    return rng.normal(size=(n, 6)) * scale


@pytest.mark.parametrize("scale", [1e-7, 1e-3, 0.5, 2.0])
def test_exp_log_match_gtsam(scale):
    for xi in random_twists(20, scale):
        T = se3.exp(xi)
        G = gtsam.Pose3.Expmap(xi).matrix()
        np.testing.assert_allclose(T, G, atol=1e-12)
        np.testing.assert_allclose(se3.log(T), gtsam.Pose3.Logmap(gtsam.Pose3(G)), atol=1e-9)


def test_log_near_pi():
    for axis in np.eye(3):
        for theta in [np.pi - 1e-6, np.pi - 1e-3, np.pi]:
            R = Rotation.from_rotvec(axis * theta).as_matrix()
            w = se3.so3_log(R)
            np.testing.assert_allclose(se3.so3_exp(w), R, atol=1e-8)


def test_batched_exp_log_and_inverse():
    xi = random_twists(50, 1.0)
    T = se3.exp(xi)
    np.testing.assert_allclose(se3.exp(se3.log(T)), T, atol=1e-10)
    np.testing.assert_allclose(se3.compose(T, se3.inverse(T)), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_adjoint_matches_gtsam_and_definition():
    for xi in random_twists(10):
        T = se3.exp(xi)
        np.testing.assert_allclose(se3.adjoint(T), gtsam.Pose3(T).AdjointMap(), atol=1e-12)
        eta = rng.normal(size=6)
        # T exp(eta) T^-1 == exp(Ad_T eta)
        np.testing.assert_allclose(T @ se3.exp(eta) @ se3.inverse(T), se3.exp(se3.adjoint(T) @ eta), atol=1e-10)


def test_quaternions_match_scipy():
    R = Rotation.random(100, random_state=1)
    q_xyzw = R.as_quat()
    q_wxyz = se3.quat_xyzw_to_wxyz(q_xyzw)
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix(q_wxyz), R.as_matrix(), atol=1e-12)
    back = se3.matrix_to_quat_wxyz(R.as_matrix())
    # same rotation up to sign
    np.testing.assert_allclose(np.abs(np.sum(back * q_wxyz, axis=1)), 1.0, atol=1e-12)
    assert np.all(back[:, 0] >= 0)
    with pytest.raises(InputError):
        se3.quat_wxyz_to_matrix(np.zeros(4))


def test_exp_torch_matches_numpy_and_is_differentiable():
    import torch

    xi = torch.tensor(random_twists(8, 0.7), dtype=torch.float64, requires_grad=True)
    np.testing.assert_allclose(se3.exp_torch(xi).detach().numpy(), se3.exp(xi.detach().numpy()), atol=1e-12)
    torch.autograd.gradcheck(lambda x: se3.exp_torch(x), (xi,))
    small = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda x: se3.exp_torch(x), (small,))


def test_camera_project_backproject_roundtrip_and_scaling():
    cam = PinholeCamera(525.0, 525.0, 319.5, 239.5, 640, 480)
    depth = rng.uniform(0.5, 5.0, size=(480, 640))
    pts = cam.backproject(depth)
    uv, z = cam.project(pts)
    v, u = np.mgrid[0:480, 0:640]
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-9)
    np.testing.assert_allclose(z, depth)
    half = cam.scaled(320, 240)
    assert half.fx == 262.5 and half.cx == 159.5 and half.cy == 119.5
    # the same ray lands on the corresponding half-resolution pixel centre
    p = np.array([0.3, -0.2, 2.0])
    uv_full, _ = cam.project(p)
    uv_half, _ = half.project(p)
    np.testing.assert_allclose((uv_full + 0.5) / 2 - 0.5, uv_half, atol=1e-9)
    with pytest.raises(InputError):
        PinholeCamera(-1, 1, 0, 0, 10, 10)
    with pytest.raises(InputError, match="depth map has shape"):
        cam.backproject(np.zeros((10, 10)))
