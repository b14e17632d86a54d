"""Global registration of two local point clouds without an initial guess: what gives ICP a start when two views
share too few image features (a wide baseline, opposite viewpoints) but see the same 3-D structure.

A cloud is prepared once (`prepare_cloud`: voxel downsampling, normals, FPFH features) and registered against any
number of others (`global_register`) by KISS-Matcher (graduated non-convexity over FPFH matches, robust to the
outlier ratios of wide baselines; the `kiss-matcher` wheel, x86-64 only) or by Open3D's FPFH + RANSAC; `refine`
then runs point-to-plane ICP on the same clouds and scores the overlap. Methods were chosen on real wide-viewpoint
pairs (docs/decisions/0009-wide-viewpoint-joins.md).

Frames: x_target = T_target_source @ x_source, clouds in metres in whatever frame the caller built them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels.errors import InputError

METHODS = ("auto", "kiss-matcher", "fpfh-ransac")


def kiss_matcher_available() -> bool:
    try:
        import kiss_matcher  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_method(method: str) -> str:
    """'auto' -> 'kiss-matcher' where the wheel is installed, else 'fpfh-ransac'; others checked."""
    if method not in METHODS:
        raise InputError(f"global registration method: expected one of {list(METHODS)}, got {method!r}")
    if method == "auto":
        return "kiss-matcher" if kiss_matcher_available() else "fpfh-ransac"
    if method == "kiss-matcher" and not kiss_matcher_available():
        raise InputError("global registration method 'kiss-matcher' needs the kiss-matcher package "
                         "(pip install kiss-matcher; x86-64 wheels only) or method 'fpfh-ransac'")
    return method


@dataclass
class PreparedCloud:
    """A cloud ready for registration: downsampled points with normals, and FPFH features computed on first use
    (ICP from a guess needs none), each once."""

    points: np.ndarray  # [N, 3] float64 metres
    normals: np.ndarray  # [N, 3] unit
    voxel: float  # metres
    pcd: object = field(repr=False)  # open3d.geometry.PointCloud (points + normals)
    prepare_s: float = 0.0
    _fpfh: object = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def fpfh(self):
        """open3d.pipelines.registration.Feature [33, N] (radius 5 voxels), computed once."""
        if self._fpfh is None:
            import open3d as o3d

            t0 = time.perf_counter()
            self._fpfh = o3d.pipelines.registration.compute_fpfh_feature(
                self.pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel, max_nn=100))
            self.prepare_s += time.perf_counter() - t0
        return self._fpfh


def prepare_cloud(points: np.ndarray, voxel: float, *, min_points: int = 200) -> PreparedCloud | None:
    """Voxel-downsample `points` [N, 3] (metres) at `voxel` and estimate normals (radius 2.5 voxels); FPFH features
    follow on first use. None when fewer than `min_points` remain: too little structure to register."""
    import open3d as o3d

    t0 = time.perf_counter()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"prepare_cloud: points must be [N, 3], got {list(pts.shape)}")
    if voxel <= 0:
        raise InputError(f"prepare_cloud: voxel must be > 0 m, got {voxel}")
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) < min_points:
        return None
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel)
    if len(pc.points) < min_points:
        return None
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    return PreparedCloud(np.asarray(pc.points).copy(), np.asarray(pc.normals).copy(), float(voxel), pc,
                         time.perf_counter() - t0)


@dataclass
class GlobalResult:
    T_target_source: np.ndarray  # [4, 4]; identity when nothing was found
    found: bool
    method: str
    inliers: int = 0  # correspondences the estimator kept
    fitness: float = 0.0  # after `refine`: fraction of source points with a target point within the ICP distance
    inlier_rmse: float = float("inf")  # metres, over those
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))  # [6, 6] twist order [omega, v]
    n_correspondences: int = 0
    time_s: float = 0.0
    reason: str = ""


def global_register(source: PreparedCloud, target: PreparedCloud, *, method: str = "auto",
                    min_inliers: int = 8, seed: int = 0) -> GlobalResult:
    """T_target_source from features alone. 'kiss-matcher': mutual FPFH matches pruned by graph-theoretic
    consistency, then a GNC-TLS rotation and translation (its own voxel = the clouds'); 'fpfh-ransac': Open3D's
    RANSAC over mutual FPFH matches (100k iterations, confidence 0.999, seeded). `found` is False when fewer than
    `min_inliers` correspondences support the estimate."""
    if abs(source.voxel - target.voxel) > 1e-9:
        raise InputError(f"global_register: clouds prepared at different voxels ({source.voxel} and {target.voxel} m)")
    method = resolve_method(method)
    t0 = time.perf_counter()
    T, inliers = np.eye(4), 0
    if method == "kiss-matcher":
        import kiss_matcher

        m = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(source.voxel))
        sol = m.estimate(source.points, target.points)
        inliers = int(m.get_num_final_inliers())
        if sol.valid:
            T[:3, :3] = np.asarray(sol.rotation)
            T[:3, 3] = np.asarray(sol.translation).reshape(3)
    else:
        import open3d as o3d

        reg = o3d.pipelines.registration
        o3d.utility.random.seed(seed)
        dist = 1.5 * source.voxel
        r = reg.registration_ransac_based_on_feature_matching(
            source.pcd, target.pcd, source.fpfh, target.fpfh, True, dist,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        T = np.asarray(r.transformation, dtype=np.float64).copy()
        inliers = int(len(r.correspondence_set))
    ok = inliers >= min_inliers and np.isfinite(T).all()
    return GlobalResult(T if ok else np.eye(4), bool(ok), method, inliers, time_s=time.perf_counter() - t0,
                        reason="" if ok else f"too few feature inliers ({inliers} < {min_inliers})")


def refine(source: PreparedCloud, target: PreparedCloud, result: GlobalResult, *,
           max_distance: float | None = None, iterations: int = 30) -> GlobalResult:
    """Point-to-plane ICP (Open3D) from result.T_target_source on the two prepared clouds, coarse (2 voxels) then
    fine (`max_distance`, default 1 voxel); fills fitness, inlier RMSE, the information matrix (twist order
    [omega, v]) and the correspondence count, and adds the time."""
    import open3d as o3d

    t0 = time.perf_counter()
    reg = o3d.pipelines.registration
    fine = float(max_distance if max_distance is not None else source.voxel)
    T = result.T_target_source
    for d in (2.0 * source.voxel, fine):
        r = reg.registration_icp(source.pcd, target.pcd, d, T, reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(max_iteration=iterations))
        T = np.asarray(r.transformation, dtype=np.float64).copy()
    info = np.asarray(reg.get_information_matrix_from_point_clouds(source.pcd, target.pcd, fine, T))
    # Open3D sums in parallel, so the last bits of its results change from run to run; rounded far below any
    # physical meaning (1e-10 m and rad, 10 significant digits), a run and its resumed twin agree bit for bit.
    T, info = np.round(T, 10), _significant(info, 10)
    out = GlobalResult(T, result.found, result.method, result.inliers, float(_significant(r.fitness, 10)),
                       float(_significant(r.inlier_rmse, 10)) if r.fitness > 0 else float("inf"), info,
                       int(len(r.correspondence_set)), result.time_s + time.perf_counter() - t0, result.reason)
    return out


def _significant(x, digits: int):
    """x (scalar or array) rounded to `digits` significant digits."""
    a = np.asarray(x, dtype=np.float64)
    mag = np.where(a != 0, np.floor(np.log10(np.abs(np.where(a != 0, a, 1.0)))), 0.0)
    scale = 10.0 ** (digits - 1 - mag)
    return np.round(a * scale) / scale
