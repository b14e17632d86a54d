"""ICP kernels against their float64 twins (kernels/_ref_icp.py), Warp against Taichi, and the twin's Jacobians
against finite differences. Frames are tiny renders of the synthetic room (80x60)."""

import numpy as np
import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import reference as R
from swarmsplat.kernels import icp as K
from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration import synthetic

W, H = 80, 60


@pytest.fixture(scope="module")
def frames():
    cam, (cs, ds), (ct, dt), T = synthetic.pair(W, H)
    rng = np.random.default_rng(0)
    # Knock out some pixels so validity gates are exercised.
    ds = ds.copy()
    ds[rng.random(ds.shape) < 0.05] = 0.0
    return cam, cs, ds, ct, dt, T


def _t(x, dev):
    return torch.from_numpy(np.ascontiguousarray(x)).to(dev)


def _setup(frames, dev):
    cam, cs, ds, ct, dt, T = frames
    tv, tn = K.vertices_normals_from_depth(_t(dt, dev), cam)
    sv, sn = K.vertices_normals_from_depth(_t(ds, dev), cam)
    # A slightly perturbed pose so residuals are not all ~0.
    Tp = se3.exp(np.array([0.004, -0.003, 0.002, 0.01, -0.005, 0.008])) @ T
    return cam, sv.reshape(-1, 3), sn.reshape(-1, 3), tv, tn, torch.from_numpy(Tp)


def test_vertices_normals_match_twin(backend, frames):
    cam, _, _, _, dt, _ = frames
    v, n = K.vertices_normals_from_depth(_t(dt, backend.torch_device), cam)
    vr, nr = R.vertices_normals_from_depth_ref(dt, cam)
    assert torch.allclose(v.cpu().double(), vr, atol=1e-5)
    assert torch.allclose(n.cpu().double(), nr, atol=1e-4)
    valid = nr.norm(dim=-1) > 0
    assert valid.float().mean() > 0.8  # the gate keeps smooth surfaces
    # Normals face the camera.
    assert ((n.cpu().double() * v.cpu().double()).sum(-1)[valid] < 0).all()


def test_projective_association_matches_twin(backend, frames):
    cam, src, sn, tv, tn, T = _setup(frames, backend.torch_device)
    idx = K.associate_projective(src, T, tv, tn, cam, max_distance=0.05, source_normals=sn, max_angle_deg=30.0)
    ref = R.associate_projective_ref(src, T, tv, tn, cam, 0.05, sn, float(np.cos(np.deg2rad(30.0))))
    assert (idx.cpu() >= 0).sum() > 0.5 * src.shape[0]
    # float32 kernels vs float64 twin: only points exactly on a rounding / gate boundary may differ.
    assert (idx.cpu() != ref).float().mean() < 2e-3


@pytest.mark.parametrize("robust", ["none", "huber", "tukey"])
def test_reduction_matches_twin(backend, frames, robust):
    cam, src, sn, tv, tn, T = _setup(frames, backend.torch_device)
    idx = K.associate_projective(src, T, tv, tn, cam, max_distance=0.05)
    scale = 0.0 if robust == "none" else 0.01
    ne = K.reduce_point_to_plane(src, T, tv, tn, idx, robust=robust, robust_scale=scale)
    ref = R.reduce_point_to_plane_ref(src, T, tv.reshape(-1, 3), tn.reshape(-1, 3), idx, robust, scale)
    assert ne.count == int(ref[44]) > 1000
    assert torch.allclose(ne.JtJ, ref[:36].reshape(6, 6), rtol=1e-4, atol=1e-6 * float(ref[:36].abs().max()))
    assert torch.allclose(ne.Jtr, ref[36:42], rtol=1e-3, atol=1e-4 * float(ref[36:42].abs().max()))
    assert ne.cost == pytest.approx(float(ref[42]), rel=1e-4)
    assert ne.dist_sq == pytest.approx(float(ref[43]), rel=1e-4)


def test_fused_step_with_photometric_term_matches_twin(backend, frames):
    cam, cs, ds, ct, dt, _ = frames
    dev = backend.torch_device
    _, src, sn, tv, tn, T = _setup(frames, dev)
    m = torch.from_numpy(ds.reshape(-1) > 0)
    src, sn = src[m.to(dev)].contiguous(), sn[m.to(dev)].contiguous()
    from swarmsplat.registration.pointcloud import gradient, intensity

    Is = _t(intensity(cs).reshape(-1)[ds.reshape(-1) > 0], dev)
    It = _t(intensity(ct), dev)
    G = gradient(It).contiguous()
    photo = K.PhotometricTerm(Is, It, G, cam, 0.2)
    ne = K.projective_normal_equations(src, T, tv, tn, cam, max_distance=0.05, source_normals=sn, max_angle_deg=40.0,
                                       robust="huber", robust_scale=0.02, photometric=photo)
    idx = R.associate_projective_ref(src, T, tv, tn, cam, 0.05, sn, float(np.cos(np.deg2rad(40.0))))
    ref = R.reduce_point_to_plane_ref(src, T, tv.reshape(-1, 3), tn.reshape(-1, 3), idx, "huber", 0.02,
                                      photometric=(Is, It, G, cam, 0.2))
    assert abs(ne.count - int(ref[44])) <= 0.002 * ne.count
    assert ne.photo_count > 1000 and abs(ne.photo_count - int(ref[46])) <= 0.002 * ne.count
    assert torch.allclose(ne.JtJ, ref[:36].reshape(6, 6), rtol=5e-3, atol=5e-3 * float(ref[:36].abs().max()))
    assert ne.photo_cost == pytest.approx(float(ref[45]), rel=1e-2)


def test_grid_nearest_neighbour_and_moments_match_twin(backend, frames):
    cam, _, ds, _, dt, _ = frames
    dev = backend.torch_device
    _, src, _, tv, _, T = _setup(frames, dev)
    tp = tv.reshape(-1, 3)
    tp = tp[tp[:, 2] > 0].contiguous()
    src = src[src[:, 2] > 0].contiguous()
    grid = K.PointGrid(tp, 0.04)
    idx = K.associate_nearest(src, T, grid, max_distance=0.04)
    ref = R.associate_nearest_ref(src, T, tp, 0.04)
    assert (idx.cpu() >= 0).sum() > 0.5 * len(src)
    assert (idx.cpu() != ref).float().mean() < 2e-3
    # Exact radius neighbourhoods through a grid whose cell differs from the radius.
    m = K.cloud_moments(grid, tp[:500], 0.07)
    mr = R.cloud_moments_ref(tp, tp[:500], 0.07)
    assert torch.equal(m[:, 0].cpu(), mr[:, 0])
    assert torch.allclose(m.cpu(), mr, rtol=1e-5, atol=1e-6)
    n = K.cloud_normals(tp, 0.07, viewpoint=(0, 0, 0), grid=K.PointGrid(tp, 0.07))
    mall = R.cloud_moments_ref(tp, tp, 0.07)
    nr = R.normals_from_moments_ref(mall, tp, viewpoint=(0, 0, 0))
    # Compare where the normal is well defined: enough neighbours and a clear smallest eigenvalue (not corners).
    c = mall.numpy()
    k = np.maximum(c[:, 0], 1)
    mu = c[:, 1:4] / k[:, None]
    C = np.stack([c[:, 4], c[:, 5], c[:, 6], c[:, 5], c[:, 7], c[:, 8], c[:, 6], c[:, 8], c[:, 9]], 1).reshape(-1, 3, 3)
    C = C / k[:, None, None] - mu[:, :, None] * mu[:, None, :]
    ev = np.linalg.eigvalsh(C)
    ok = torch.from_numpy((c[:, 0] >= 3) & (ev[:, 0] < 0.3 * ev[:, 1]))
    assert ok.float().mean() > 0.8
    cos = (n.cpu().double() * nr).sum(1)[ok]
    assert (cos > 0.999).float().mean() > 0.999


def test_warp_equals_taichi(frames):
    out = {}
    for name in ("warp", "taichi"):
        b = kernels.use(name, "cpu")
        cam, src, sn, tv, tn, T = _setup(frames, b.torch_device)
        ne = K.projective_normal_equations(src, T, tv, tn, cam, max_distance=0.05, source_normals=sn,
                                           max_angle_deg=30.0, robust="tukey", robust_scale=0.02)
        tp = tv.reshape(-1, 3)[tv.reshape(-1, 3)[:, 2] > 0].contiguous()
        nn = K.associate_nearest(src, T, K.PointGrid(tp, 0.05), max_distance=0.05)
        out[name] = (tv, tn, ne, nn)
    (tv_w, tn_w, ne_w, nn_w), (tv_t, tn_t, ne_t, nn_t) = out["warp"], out["taichi"]
    assert torch.allclose(tv_w, tv_t, atol=1e-6) and torch.allclose(tn_w, tn_t, atol=1e-5)
    assert ne_w.count == ne_t.count
    assert torch.allclose(ne_w.JtJ, ne_t.JtJ, rtol=1e-4, atol=1e-6 * float(ne_w.JtJ.abs().max()))
    assert torch.allclose(ne_w.Jtr, ne_t.Jtr, rtol=1e-3, atol=1e-4 * float(ne_w.Jtr.abs().max()))
    assert (nn_w != nn_t).float().mean() < 1e-3


def test_twin_jacobian_matches_finite_differences():
    """Jtr of the twin is the gradient of 0.5 * sum r^2 wrt the left twist, for both terms (fixed associations)."""
    rng = np.random.default_rng(1)
    cam = synthetic.default_camera(40, 30)
    N = 200
    src = torch.from_numpy(np.c_[rng.uniform(-0.5, 0.5, (N, 2)), rng.uniform(1.5, 2.5, N)].astype(np.float32))
    tp = torch.from_numpy(rng.normal(size=(N, 3)).astype(np.float32))
    tn = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(N, 3)).astype(np.float32)), dim=1)
    idx = torch.arange(N, dtype=torch.int32)
    v, u = np.mgrid[0:30, 0:40].astype(np.float64)
    It = torch.from_numpy((0.01 * u + 0.02 * v + 0.1).astype(np.float32))  # linear: bilinear and central diffs exact
    G = torch.from_numpy(np.stack([np.full_like(u, 0.01), np.full_like(v, 0.02)], -1).astype(np.float32))
    Is = torch.from_numpy(rng.uniform(0, 1, N).astype(np.float32))
    photo = (Is, It, G, cam, 0.5)
    T0 = se3.exp(np.array([0.01, -0.02, 0.015, 0.02, 0.01, -0.03]))

    def cost(xi):
        s = R.reduce_point_to_plane_ref(src, se3.exp(xi) @ T0, tp, tn, idx, photometric=photo)
        return 0.5 * float(s[42] + s[45])

    s0 = R.reduce_point_to_plane_ref(src, T0, tp, tn, idx, photometric=photo)
    assert s0[46] > 50
    eps = 1e-6
    num = np.array([(cost(eps * e) - cost(-eps * e)) / (2 * eps) for e in np.eye(6)])
    assert np.allclose(s0[36:42].numpy(), num, rtol=1e-4, atol=1e-7)


def test_kernel_inputs_are_checked(backend, frames):
    cam, src, sn, tv, tn, T = _setup(frames, backend.torch_device)
    bad = src.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(InputError, match="argument 'source_points': contains NaN"):
        K.associate_projective(bad, T, tv, tn, cam, max_distance=0.05)
    with pytest.raises(InputError, match="argument 'target_vertices': expected shape"):
        K.associate_projective(src, T, tv[1:], tn, cam, max_distance=0.05)
    with pytest.raises(InputError, match="argument 'idx': expected dtype"):
        K.reduce_point_to_plane(src, T, tv, tn, torch.zeros(src.shape[0], dtype=torch.int64, device=src.device))
    with pytest.raises(InputError, match="argument 'robust'"):
        K.reduce_point_to_plane(src, T, tv, tn, torch.zeros(src.shape[0], dtype=torch.int32, device=src.device),
                                robust="cauchy")
    with pytest.raises(InputError, match="argument 'T_target_source': expected shape"):
        K.associate_projective(src, T[:3], tv, tn, cam, max_distance=0.05)
    with pytest.raises(InputError, match="argument 'depth': expected dtype"):
        K.vertices_normals_from_depth(torch.zeros(cam.height, cam.width, dtype=torch.float64), cam)
