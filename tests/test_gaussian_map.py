"""Gaussian map, submap transforms (eq. 15), 3DGS PLY I/O and the typed config."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.gaussian_map import GaussianMap, GaussianParams, transform_params
from swarmsplat.slam.dense.ply import load_ply, save_ply


def random_params(n: int, seed: int = 0) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    return GaussianParams(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 3, generator=g) * 0.3 - 3.0,
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g),
        torch.rand(n, 3, generator=g),
    )


def covariance(p: GaussianParams) -> np.ndarray:
    q = p.quats.double().numpy()
    R = se3.quat_wxyz_to_matrix(q)
    S = np.exp(p.log_scales.double().numpy())
    M = R * S[:, None, :]
    return M @ np.swapaxes(M, 1, 2)


def test_transform_moves_means_and_rotates_covariances():
    p = random_params(50)
    T = se3.exp(np.array([0.3, -0.2, 0.5, 1.0, -2.0, 0.5]))
    q = transform_params(p, T)
    R, t = T[:3, :3], T[:3, 3]
    np.testing.assert_allclose(q.means.double().numpy(), p.means.double().numpy() @ R.T + t, atol=1e-5)
    np.testing.assert_allclose(covariance(q), R @ covariance(p) @ R.T, atol=1e-5)
    # opacity, colour, scales untouched; the input is not modified
    assert torch.equal(q.colors, p.colors) and torch.equal(q.logit_opacities, p.logit_opacities)
    assert torch.equal(q.log_scales, p.log_scales)
    # composing two transforms equals transforming by their product
    T2 = se3.exp(np.array([-0.1, 0.4, 0.2, 0.0, 0.3, -1.0]))
    a, b = transform_params(transform_params(p, T), T2), transform_params(p, T2 @ T)
    np.testing.assert_allclose(a.means.numpy(), b.means.numpy(), atol=1e-5)
    np.testing.assert_allclose(covariance(a), covariance(b), atol=1e-5)


def test_map_submaps_merge_and_prune():
    m = GaussianMap()
    s0 = m.new_submap(np.eye(4))
    m.add(s0, random_params(10, 1))
    T1 = se3.exp(np.array([0.0, 0.5, 0.0, 2.0, 0.0, 0.0]))
    s1 = m.new_submap(T1)
    m.add(s1, random_params(7, 2))
    assert m.active is s1 and len(m) == 17
    merged = m.merged()
    np.testing.assert_allclose(merged.means[10:].numpy(), transform_params(s1.params, T1).means.numpy(), atol=1e-6)
    # moving a submap moves its world Gaussians, not its local parameters
    D = se3.exp(np.array([0.1, 0.0, 0.0, 0.0, 1.0, 0.0]))
    local_before = s1.params.means.clone()
    m.transform_submap(s1, D)
    assert torch.equal(s1.params.means, local_before)
    np.testing.assert_allclose(m.merged().means[10:].numpy(),
                               transform_params(s1.params, D @ T1).means.numpy(), atol=1e-6)
    # prune by opacity and size
    s1.params.logit_opacities[:3] = -10.0
    s1.params.log_scales[3] = np.log(2.0)
    removed = m.prune(s1, min_opacity=0.05, max_scale=1.0)
    assert removed == 4 and len(s1) == 3


def test_ply_round_trip(tmp_path):
    p = random_params(100, 3)
    path = save_ply(tmp_path / "map.ply", p)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    for prop in ["x", "nx", "f_dc_0", "f_dc_2", "opacity", "scale_2", "rot_0", "rot_3"]:
        assert f"property float {prop}\n" in header
    q = load_ply(path)
    for a, b in zip(p.tensors(), q.tensors()):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-6)
    # colour convention: f_dc = (rgb - 0.5) / C0
    data = np.frombuffer(path.read_bytes()[len(header) + len("end_header\n"):], dtype="<f4").reshape(100, 17)
    np.testing.assert_allclose(data[:, 6:9], (p.colors.numpy() - 0.5) / 0.28209479, atol=1e-5)
    # empty map round-trips too
    assert len(load_ply(save_ply(tmp_path / "empty.ply", GaussianParams.empty()))) == 0


def test_ply_malformed_files(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(InputError, match="not a PLY"):
        load_ply(bad)
    good = save_ply(tmp_path / "g.ply", random_params(10))
    (tmp_path / "trunc.ply").write_bytes(good.read_bytes()[:-20])
    with pytest.raises(InputError, match="truncated"):
        load_ply(tmp_path / "trunc.ply")
    (tmp_path / "nogauss.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + np.zeros(3, "<f4").tobytes())
    with pytest.raises(InputError, match="missing vertex properties"):
        load_ply(tmp_path / "nogauss.ply")
    with pytest.raises(InputError, match="not found"):
        load_ply(tmp_path / "absent.ply")


def test_config_yaml_round_trip_and_validation(tmp_path):
    cfg = SlamConfig()
    again = SlamConfig.from_yaml(_write(tmp_path / "c.yaml", cfg.to_yaml()))
    assert again == cfg
    cfg2 = SlamConfig.from_yaml(_write(tmp_path / "o.yaml", "mapping:\n  iterations: 7\n"),
                                overrides={"kernels": {"backend": "taichi"}})
    assert cfg2.mapping.iterations == 7 and cfg2.kernels.backend == "taichi"
    assert cfg2.tracking == cfg.tracking
    with pytest.raises(InputError, match="mapping.iterations"):
        SlamConfig.from_yaml(_write(tmp_path / "b.yaml", "mapping:\n  iterations: -1\n"))
    with pytest.raises(InputError, match="tracking.nonsense"):
        SlamConfig.from_yaml(_write(tmp_path / "u.yaml", "tracking:\n  nonsense: 1\n"))
    with pytest.raises(InputError, match="invalid YAML"):
        SlamConfig.from_yaml(_write(tmp_path / "y.yaml", "mapping: [\n"))


def _write(path, text):
    path.write_text(text)
    return path


def test_frames_follow_their_keyframes_refined_pose():
    """slam.dense.submaps.frame_local_poses: after a keyframe whose pose the map refinement refined, a frame of the same
    submap keeps its tracked pose relative to that keyframe; frames before it, in another submap, or after an
    unrefined keyframe keep their tracked pose; Keyframe.T_local prefers the refined pose."""
    from swarmsplat.slam.dense.agent import FramePose
    from swarmsplat.slam.dense.submaps import Keyframe, frame_local_poses

    T = [se3.exp(np.array([0.0, 0.01 * i, 0.0, 0.1 * i, 0.0, 0.02 * i])) for i in range(7)]
    poses = [FramePose(i, float(i), 0 if i < 5 else 1, T[i]) for i in range(7)]
    fix = se3.exp(np.array([0.002, 0.0, -0.001, 0.004, 0.003, 0.0]))
    kfs = [Keyframe(0, 0, 0.0, 0, T[0], None, None), Keyframe(1, 2, 2.0, 0, T[2], None, None),
           Keyframe(2, 4, 4.0, 0, T[4], None, None), Keyframe(3, 5, 5.0, 1, T[5], None, None)]
    kfs[1].T_local_refined = T[2] @ fix
    assert np.array_equal(kfs[0].T_local, T[0]) and np.array_equal(kfs[1].T_local, T[2] @ fix)
    local = frame_local_poses(poses, kfs)
    for i in (0, 1, 4, 5, 6):  # before the refined keyframe, after an unrefined one, another submap
        assert np.array_equal(local[i], T[i])
    for i in (2, 3):  # the refined keyframe's own frame and the frame tracked after it
        assert np.allclose(local[i], T[2] @ fix @ se3.inverse(T[2]) @ T[i], atol=1e-12)
    assert not np.allclose(local[3], T[3], atol=1e-4)
