"""Registration on generated frames, on the Redwood living-room frames, and against Open3D's registration_icp;
failure results (not exceptions, not garbage poses) for planes, few points and empty depth; input errors."""

import numpy as np
import pytest

from swarmsplat import kernels
from conftest import shared_data
from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration import result as R
from swarmsplat.registration import synthetic
from swarmsplat.registration.icp import icp_clouds, icp_rgbd
from swarmsplat.registration.pointcloud import depth_to_points, select_rows, voxel_downsample
from swarmsplat.registration.rgbd import register_rgbd, rgbd_odometry


def pose_error(T, T_true):
    D = se3.inverse(T_true) @ T
    return np.linalg.norm(D[:3, 3]), np.rad2deg(se3.rotation_angle(D[:3, :3]))


@pytest.fixture(scope="module")
def small_pair():
    return synthetic.pair(160, 120)


@pytest.fixture(scope="module")
def mid_pair():
    return synthetic.pair(320, 240)


def test_select_rows_equals_boolean_indexing():
    import torch

    g = torch.Generator().manual_seed(0)
    m = torch.rand(24, 32, generator=g) > 0.4
    a, b = torch.randn(24 * 32, 3, generator=g), torch.arange(24 * 32, dtype=torch.int32)
    ra, rb = select_rows(m, a, b)
    flat = m.reshape(-1)
    assert torch.equal(ra, a[flat]) and torch.equal(rb, b[flat]) and ra.is_contiguous()
    assert [t.shape[0] for t in select_rows(torch.zeros(5, dtype=torch.bool), a[:5])] == [0]


def test_icp_rgbd_recovers_a_known_motion(backend, small_pair):
    cam, (cs, ds), (ct, dt), T = small_pair  # 54 mm / 2.7 deg apart
    # Geometry alone, from a guess 3 cm / 1.5 deg off (the fine stage's job).
    init = se3.exp(np.array([0.015, -0.01, 0.015, 0.02, -0.015, 0.015])) @ T
    r = icp_rgbd(ds, dt, cam, init)
    assert r.success and r.reason == R.OK, r
    et, er = pose_error(r.T_target_source, T)
    assert et < 1e-3 and er < 0.05
    # With the colour term, from identity.
    rh = icp_rgbd(ds, dt, cam, source_color=cs, target_color=ct, photometric_weight=0.3)
    assert rh.success, rh
    et, er = pose_error(rh.T_target_source, T)
    assert et < 1e-3 and er < 0.05
    assert r.fitness > 0.8 and 0 < r.inlier_rmse < 0.02 and r.n_correspondences > 10000
    assert np.allclose(r.information, r.information.T) and np.linalg.eigvalsh(r.information).min() > 0


def test_coarse_hybrid_odometry_recovers_5cm_3deg(mid_pair):
    kernels.use("taichi", "cpu")
    cam, (cs, ds), (ct, dt), T = mid_pair
    r = rgbd_odometry(cs, ds, ct, dt, cam)
    assert r.success, r
    et, er = pose_error(r.T_target_source, T)
    assert et < 1e-3 and er < 0.05


def _redwood():
    import cv2

    root = shared_data("redwood_livingroom1_rgbd5")
    K = __import__("json").loads((root / "camera_primesense.json").read_text())["intrinsic_matrix"]
    cam = PinholeCamera(K[0], K[4], K[6], K[7], 640, 480)  # column-major 3x3
    frames = []
    for i in range(5):
        d = cv2.imread(str(root / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
        c = cv2.cvtColor(cv2.imread(str(root / "color" / f"{i:05d}.jpg")), cv2.COLOR_BGR2RGB)
        frames.append((c, d))
    lines = (root / "trajectory.log").read_text().split("\n")
    T_world_cam = [np.array([[float(x) for x in lines[5 * k + 1 + r].split()] for r in range(4)]) for k in range(5)]
    return cam, frames, T_world_cam


@pytest.fixture(scope="module")
def redwood():
    return _redwood()


def test_icp_rgbd_on_redwood_frames(backend, redwood):
    cam, frames, T_wc = redwood
    assert cam.fx == 525.0 and cam.cx == 319.5
    for s, t in [(1, 0), (2, 1), (3, 2), (4, 3), (4, 0)]:
        r = icp_rgbd(frames[s][1], frames[t][1], cam)
        assert r.success, (s, t, r)
        et, er = pose_error(r.T_target_source, se3.inverse(T_wc[t]) @ T_wc[s])
        assert et < 5e-3 and er < 0.5, (s, t, et, er)
        assert r.passes(0.5, 0.1)


def test_odometry_scored_on_every_other_pixel_agrees_with_the_full_score(redwood):
    """eval_stride 2 (the tracker's coarse stage at 320 px: tracking.coarse_eval_max_width) moves nothing and scores
    the same pose from a quarter of the source pixels against the whole target: fitness within 0.02, RMSE within
    5 %, the information per correspondence (what the pose graph's covariance uses) within 3 % (sampling, not
    rounding: measured 0.005, 2 % and 0.5 % on these pairs)."""
    import cv2

    kernels.use("warp", "cpu")
    cam0, frames, _ = redwood
    cam = cam0.scaled(320, 240)
    small = [(cv2.resize(c, (320, 240), interpolation=cv2.INTER_AREA), d[::2, ::2].copy()) for c, d in frames]
    for s, t in [(1, 0), (2, 1), (3, 2), (4, 3)]:
        a = rgbd_odometry(*small[s], *small[t], cam, depth_max=10.0)
        b = rgbd_odometry(*small[s], *small[t], cam, depth_max=10.0, eval_stride=2)
        assert a.success and b.success and np.array_equal(a.T_target_source, b.T_target_source)
        assert 0.2 < b.n_correspondences / a.n_correspondences < 0.3
        assert abs(b.fitness - a.fitness) < 0.02 and abs(b.inlier_rmse / a.inlier_rmse - 1) < 0.05
        Ha, Hb = a.information / a.n_correspondences, b.information / b.n_correspondences
        assert np.abs(Hb - Ha).max() < 0.03 * np.abs(Ha).max()


def test_register_rgbd_on_redwood_is_tighter_with_colour(redwood):
    kernels.use("warp", "cpu")
    cam, frames, T_wc = redwood
    r = register_rgbd(frames[4][0], frames[4][1], frames[0][0], frames[0][1], cam)
    assert r.success and r.method.startswith("register_rgbd"), r
    et, er = pose_error(r.T_target_source, se3.inverse(T_wc[0]) @ T_wc[4])
    assert et < 2.5e-3 and er < 0.1


def test_register_rgbd_falls_back_to_global_registration_when_far_off():
    kernels.use("taichi", "cpu")
    cam, (cs, ds), (ct, dt), T = synthetic.pair(320, 240, (0.25, 0.1, -0.1), (-6.0, 10.0, 4.0))  # 29 cm / 12 deg
    r = register_rgbd(cs, ds, ct, dt, cam)
    assert r.success and r.method == "register_rgbd/global", r
    et, er = pose_error(r.T_target_source, T)
    assert et < 1e-3 and er < 0.05


def test_icp_clouds_matches_open3d_point_to_plane(backend, mid_pair):
    o3d = pytest.importorskip("open3d")
    cam, (cs, ds), (ct, dt), T = mid_pair
    src = voxel_downsample(depth_to_points(ds, cam)[0], 0.03)[0]
    tgt = voxel_downsample(depth_to_points(dt, cam)[0], 0.03)[0]
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.astype(np.float64)))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.astype(np.float64)))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.08, max_nn=30))
    normals = np.asarray(pt.normals).astype(np.float32)
    init = se3.exp(np.array([0.01, -0.01, 0.005, 0.02, 0.01, -0.02])) @ T  # ~3 cm / 1 deg off
    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=50)
    ref = reg.registration_icp(ps, pt, 0.06, init, reg.TransformationEstimationPointToPlane(), crit)
    ours = icp_clouds(src, tgt, init, max_distance=0.06, target_normals=normals, max_iterations=50)
    assert ours.success, ours
    et, er = pose_error(ours.T_target_source, np.asarray(ref.transformation))
    assert et < 1e-3 and er < 0.05
    assert ours.fitness == pytest.approx(ref.fitness, rel=0.01)
    assert ours.inlier_rmse == pytest.approx(ref.inlier_rmse, rel=0.01)
    info = reg.get_information_matrix_from_point_clouds(ps, pt, 0.06, ours.T_target_source)
    assert np.allclose(ours.information, np.asarray(info), rtol=0.01, atol=1e-3 * np.abs(info).max())
    # And it found the true motion (up to what voxelisation allows).
    et, er = pose_error(ours.T_target_source, T)
    assert et < 0.01 and er < 0.3


def test_icp_clouds_estimates_normals_itself(mid_pair):
    kernels.use("warp", "cpu")
    cam, (cs, ds), (ct, dt), T = mid_pair
    src = voxel_downsample(depth_to_points(ds, cam)[0], 0.04)[0]
    tgt = voxel_downsample(depth_to_points(dt, cam)[0], 0.04)[0]
    r = icp_clouds(src, tgt, np.eye(4), max_distance=0.1, normal_radius=0.1)
    assert r.success, r
    et, er = pose_error(r.T_target_source, T)
    assert et < 0.01 and er < 0.3


# ---- failures: a reason, the initial pose back, never an exception ------------------------------------------


def test_plane_is_degenerate_not_a_pose(backend):
    cam = synthetic.default_camera(80, 60)
    wall = np.full((60, 80), 2.0, np.float32)
    init = se3.exp(np.array([0.0, 0.0, 0.01, 0.02, 0.0, 0.0]))
    r = icp_rgbd(wall, wall, cam, init)
    assert not r.success and r.reason == R.DEGENERATE
    assert np.array_equal(r.T_target_source, init)
    pts = depth_to_points(wall, cam)[0]
    rc = icp_clouds(pts, pts, init, max_distance=0.05)
    assert not rc.success and rc.reason == R.DEGENERATE and np.array_equal(rc.T_target_source, init)


def test_empty_or_tiny_inputs_fail_with_a_reason(backend, small_pair):
    cam, (cs, ds), (ct, dt), T = small_pair
    empty = np.zeros_like(ds)
    r = icp_rgbd(empty, dt, cam)
    assert not r.success and r.reason == R.TOO_FEW_POINTS and np.array_equal(r.T_target_source, np.eye(4))
    few = np.zeros_like(ds)
    few[50:53, 60:64] = ds[50:53, 60:64]
    assert icp_rgbd(few, dt, cam).reason == R.TOO_FEW_POINTS
    pts = depth_to_points(dt, cam)[0]
    r = icp_clouds(pts[:5], pts, np.eye(4), max_distance=0.05)
    assert not r.success and r.reason == R.TOO_FEW_POINTS
    # No overlap at all: the source far outside the target's range.
    far = pts[::50] + np.float32([50.0, 0.0, 0.0])
    r = icp_clouds(far, pts, np.eye(4), max_distance=0.05)
    assert not r.success and r.reason == R.TOO_FEW_POINTS


def test_bad_inputs_raise_input_errors_naming_the_argument(small_pair):
    kernels.use("warp", "cpu")
    cam, (cs, ds), (ct, dt), T = small_pair
    nan = ds.copy()
    nan[3, 4] = np.nan
    with pytest.raises(InputError, match="'source_depth'.*NaN"):
        icp_rgbd(nan, dt, cam)
    with pytest.raises(InputError, match="'target_depth'.*float32"):
        icp_rgbd(ds, (dt * 1000).astype(np.uint16), cam)
    with pytest.raises(InputError, match="'source_depth'.*shape"):
        icp_rgbd(ds[:-1], dt, cam)
    with pytest.raises(InputError, match="'init'.*rigid"):
        icp_rgbd(ds, dt, cam, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(InputError, match="'source_color'"):
        rgbd_odometry(cs.astype(np.float32), ds, ct, dt, cam)
    with pytest.raises(InputError, match="'camera'"):
        icp_rgbd(ds, dt, cam.K)
    pts = depth_to_points(dt, cam)[0]
    bad = pts.copy()
    bad[0, 0] = np.inf
    with pytest.raises(InputError, match="'target_points'.*NaN"):
        icp_clouds(pts, bad, np.eye(4), max_distance=0.05)
    with pytest.raises(InputError, match="'target_normals'.*shape"):
        icp_clouds(pts, pts, np.eye(4), max_distance=0.05, target_normals=pts[:10])


def test_views_without_overlap_fail_with_the_initial_pose():
    kernels.use("taichi", "cpu")
    cam = synthetic.default_camera(160, 120)
    ca, da = synthetic.render(cam, synthetic.pose((0.1, -0.1, -0.5), (-5.0, 8.0, 0.0)))
    cb, db = synthetic.render(cam, synthetic.pose((0.3, -0.1, 1.0), (0.0, 180.0, 0.0)))  # facing the other way
    init = se3.exp(np.array([0.0, 0.1, 0.0, 0.05, 0.0, 0.0]))
    r = register_rgbd(ca, da, cb, db, cam, init)
    assert not r.success and r.reason in (R.TOO_FEW_POINTS, R.POOR_ALIGNMENT, R.DEGENERATE), r
    assert np.array_equal(r.T_target_source, init)


def test_open3d_odometry_methods_are_scored_with_our_evaluation(mid_pair):
    kernels.use("warp", "cpu")
    cam, (cs, ds), (ct, dt), T = mid_pair
    r = rgbd_odometry(cs, ds, ct, dt, cam, method="open3d-point-to-plane")
    assert r.success and r.method == "rgbd_odometry/open3d-point-to-plane" and r.fitness > 0.8
    et, er = pose_error(r.T_target_source, T)
    assert et < 3e-3 and er < 0.1
    with pytest.raises(InputError, match="'method'"):
        rgbd_odometry(cs, ds, ct, dt, cam, method="sift")
