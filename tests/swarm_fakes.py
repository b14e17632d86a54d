"""Stand-ins for the place recogniser and pair registrar in the swarm runtime tests (fast, exact, deterministic).

A fake keyframe "image" is the bytes of its ground-truth pose (float64 [4, 4]) plus a place id: the recogniser
returns the place's unit vector, the registrar returns the true relative pose with a unit translation. Tests
of the runtime then check the protocol and the estimates, not the front-end (which has its own tests).
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.registration.pair.base import Encoding, PairRegistrar, PairResult

N_PLACES = 12
CAMERA = PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100)


def fake_image(T_world_cam: np.ndarray, place: int) -> np.ndarray:
    return np.frombuffer(np.asarray(T_world_cam, np.float64).tobytes() + bytes([place]), np.uint8).copy()


class FakeRecognizer:
    dim = N_PLACES

    def describe(self, image: np.ndarray) -> np.ndarray:
        d = np.zeros(N_PLACES, np.float32)
        d[int(image[-1])] = 1.0
        return d


class FakeRegistrar(PairRegistrar):
    name = "fake"

    def encode(self, image: np.ndarray) -> Encoding:
        return Encoding("fake", (CAMERA.width, CAMERA.height), {"T": np.frombuffer(image[:128].tobytes(), np.float64)
                                                                .reshape(4, 4)})

    def register(self, enc_query, enc_match, camera_query, camera_match=None) -> PairResult:
        T = se3.inverse(enc_query.arrays["T"]) @ enc_match.arrays["T"]
        n = np.linalg.norm(T[:3, 3])
        return PairResult(T[:3, :3], T[:3, 3] / n, 100, 120, True)


def scenario(n_robots: int = 3, n_kf: int = 12, seed: int = 0):
    """Robots walking one circle of N_PLACES places from different starts, with drifting odometry in their own
    frames. Returns per robot: (images, T_odom_kf [n_kf, 4, 4], T_world_gt [n_kf, 4, 4])."""
    rng = np.random.default_rng(seed)
    out = []
    for r in range(n_robots):
        gt, imgs = [], []
        for k in range(n_kf):
            place = (4 * r + k) % N_PLACES
            a = 2 * np.pi * place / N_PLACES
            R = se3.so3_exp(np.array([0.0, 0.0, a + np.pi / 2]))
            gt.append(se3.make(R, np.array([3 * np.cos(a), 3 * np.sin(a), 0.1 * r])))
            imgs.append(fake_image(gt[-1], place))
        gt = np.stack(gt)
        odo = [np.eye(4)]
        for k in range(1, n_kf):
            rel = se3.inverse(gt[k - 1]) @ gt[k]
            noise = se3.exp(np.concatenate([[0, 0, 0.015], rng.normal(size=3) * 0.01]))  # yaw bias: drift
            odo.append(odo[-1] @ rel @ noise)
        out.append((imgs, np.stack(odo), gt))
    return out
