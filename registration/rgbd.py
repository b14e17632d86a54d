"""Coarse RGB-D registration (paper eq. 7) and the full loop-candidate pipeline (coarse -> ICP -> gate).

`rgbd_odometry` is the coarse stage: hybrid colour-depth alignment over a strided pyramid on our kernels
(point-to-plane + photometric term, one fused pass per step). Open3D's own RGB-D odometry is available through
`method=` for comparison; on a synthetic 640x480 pair 5 cm / 3 deg apart, its hybrid term converged 44 mm off
(tensor, default weights) while ours reached 0.03 mm and still converged at 19 cm / 10 deg (measurements in
perf/icp.py and the README). `global_registration` (FPFH + RANSAC, Open3D) is the fallback when the initial
guess is far off. `register_rgbd` chains them and applies the fitness / RMSE gate.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from .icp import default_strides, evaluate_rgbd, icp_rgbd
from .pointcloud import check_camera, check_color, check_depth, check_pose, depth_to_points
from .result import POOR_ALIGNMENT, TOO_FEW_POINTS, RegistrationResult

OPEN3D_METHODS = {"open3d-hybrid": "Hybrid", "open3d-intensity": "Intensity", "open3d-point-to-plane": "PointToPlane"}


def rgbd_odometry(source_color: np.ndarray, source_depth: np.ndarray,  # [H, W, 3] uint8, [H, W] metres
                  target_color: np.ndarray, target_depth: np.ndarray, camera: PinholeCamera,
                  init: np.ndarray = np.eye(4), *, method: str = "hybrid", photometric_weight: float = 0.3,
                  strides: Sequence[int] | None = None, iterations: Sequence[int] | None = None,
                  max_distance: float = 0.05, depth_max: float | None = None,
                  pyramids: tuple | None = None, eval_stride: int = 1) -> RegistrationResult:
    """Coarse frame-to-frame alignment T_target_source from colour and depth.

    method "hybrid" (default): our projective point-to-plane + intensity term with weight `photometric_weight`
    (intensity in [0, 1] against metres; 0.1-0.3 measured equally good) on the pyramid of `icp_rgbd` without its
    full-resolution level (640x480: strides 8, 4, 2), which is left to the refinement. "geometric": the same
    without colour. "open3d-hybrid" / "open3d-intensity" /
    "open3d-point-to-plane": Open3D's tensor `rgbd_odometry_multi_scale` (10/5/3 iterations, depth_diff 0.2 m),
    scored with our evaluation. fitness / RMSE use projective correspondences within `max_distance`.
    `pyramids`: the two frames' registration.pyramid.FramePyramid, kept between calls; `eval_stride`: fitness,
    RMSE and information from every s-th pixel ("hybrid", "geometric").
    """
    camera = check_camera(camera)
    check_color("source_color", source_color, camera)
    check_color("target_color", target_color, camera)
    if method in ("hybrid", "geometric"):
        if strides is None:
            strides = default_strides(camera.width)
            strides = strides[:-1] if len(strides) > 1 else strides
        colors = dict(source_color=source_color, target_color=target_color) if method == "hybrid" else {}
        res = icp_rgbd(source_depth, target_depth, camera, init, max_distance=max_distance, strides=strides,
                       iterations=iterations, photometric_weight=photometric_weight if colors else 0.0,
                       depth_max=depth_max, pyramids=pyramids, eval_stride=eval_stride, **colors)
        res.method = f"rgbd_odometry/{method}"
        return res
    if method not in OPEN3D_METHODS:
        raise InputError(f"argument 'method': expected 'hybrid', 'geometric' or one of {sorted(OPEN3D_METHODS)}, "
                         f"got {method!r}")
    sd = check_depth("source_depth", source_depth, camera)
    td = check_depth("target_depth", target_depth, camera)
    T0 = check_pose("init", init)
    T = _open3d_odometry(source_color, sd, target_color, td, camera, T0, OPEN3D_METHODS[method], depth_max)
    if T is None:
        return RegistrationResult.failure(T0, TOO_FEW_POINTS, f"rgbd_odometry/{method}")
    res = evaluate_rgbd(sd, td, camera, T, max_distance=max_distance, depth_max=depth_max,
                        method=f"rgbd_odometry/{method}")
    if not res.success:
        res.T_target_source = T0.copy()  # a failure carries the initial guess, never the rejected pose
    return res


def _open3d_odometry(sc, sd, tc, td, camera, T0, method_name, depth_max):
    import open3d as o3d

    odo = o3d.t.pipelines.odometry

    def rgbd(c, d):
        return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(np.ascontiguousarray(c)),
                                        o3d.t.geometry.Image(np.ascontiguousarray(d, dtype=np.float32)))

    if (sd > 0).sum() < 100 or (td > 0).sum() < 100:
        return None
    K = o3d.core.Tensor(camera.K, o3d.core.Dtype.Float64)
    res = odo.rgbd_odometry_multi_scale(rgbd(sc, sd), rgbd(tc, td), K, o3d.core.Tensor(T0), 1.0,
                                        float(depth_max or 1e3), [odo.OdometryConvergenceCriteria(i) for i in (10, 5, 3)],
                                        getattr(odo.Method, method_name), odo.OdometryLossParams(0.2, 0.5, 0.5))
    T = res.transformation.numpy().astype(np.float64)
    return T if np.isfinite(T).all() else None


def global_registration(source_depth: np.ndarray, target_depth: np.ndarray, camera: PinholeCamera, *,
                        voxel: float = 0.05, depth_max: float | None = None, seed: int = 0) -> RegistrationResult:
    """FPFH features + RANSAC (Open3D) on voxelised clouds: a pose with no initial guess.

    Normals within 2 voxels, FPFH within 5 voxels, RANSAC inlier distance 1.5 voxels with edge-length (0.9) and
    distance checkers, 100k iterations at confidence 0.999, seeded for repeatability. fitness / RMSE are
    Open3D's on the voxelised clouds; refine with `icp_rgbd` before trusting the pose.
    """
    import open3d as o3d

    camera = check_camera(camera)
    sd = check_depth("source_depth", source_depth, camera)
    td = check_depth("target_depth", target_depth, camera)
    reg = o3d.pipelines.registration
    clouds, feats = [], []
    for d in (sd, td):
        pts, _ = depth_to_points(d, camera, depth_max=depth_max or np.inf)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64))).voxel_down_sample(voxel)
        if len(pc.points) < 30:
            return RegistrationResult.failure(np.eye(4), TOO_FEW_POINTS, "fpfh_ransac")
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        feats.append(reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)))
        clouds.append(pc)
    o3d.utility.random.seed(seed)
    dist = 1.5 * voxel
    r = reg.registration_ransac_based_on_feature_matching(
        clouds[0], clouds[1], feats[0], feats[1], False, dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    T = np.asarray(r.transformation, dtype=np.float64)
    if len(r.correspondence_set) < 3:
        return RegistrationResult.failure(np.eye(4), TOO_FEW_POINTS, "fpfh_ransac")
    return RegistrationResult(T, True, fitness=float(r.fitness), inlier_rmse=float(r.inlier_rmse),
                              n_correspondences=len(r.correspondence_set), method="fpfh_ransac")


def register_rgbd(source_color: np.ndarray, source_depth: np.ndarray, target_color: np.ndarray,
                  target_depth: np.ndarray, camera: PinholeCamera, init: np.ndarray = np.eye(4), *,
                  max_distance: float = 0.05, min_fitness: float = 0.5, max_rmse: float = 0.1,
                  coarse_method: str = "hybrid", refine_photometric_weight: float = 0.3, global_fallback: bool = True,
                  voxel: float = 0.05, depth_max: float | None = None) -> RegistrationResult:
    """Loop-candidate registration: coarse RGB-D odometry -> point-to-plane ICP -> fitness / RMSE gate.

    The refinement is point-to-plane ICP (eq. 8) plus the intensity term with `refine_photometric_weight`
    (0 gives pure eq. 8): on the Redwood living-room frames with noisy depth the term cut the error of frame
    4 -> 0 from 3.7 mm to 1.3 mm (0.3) and frame-to-frame errors from ~1 mm to ~0.3 mm.

    When the result fails the gate (fitness > `min_fitness`, inlier RMSE < `max_rmse` metres) and
    `global_fallback` is set, FPFH + RANSAC provides a new start for ICP and the better-scoring result is kept.
    A result that still fails the gate comes back with success False and reason "poor alignment" (or the
    ICP's own reason), its pose the initial guess.
    """
    T0 = check_pose("init", init)
    coarse = rgbd_odometry(source_color, source_depth, target_color, target_depth, camera, T0,
                           method=coarse_method, max_distance=max_distance, depth_max=depth_max)
    start = coarse.T_target_source if coarse.success else T0
    colors = dict(source_color=source_color, target_color=target_color, photometric_weight=refine_photometric_weight)
    best = icp_rgbd(source_depth, target_depth, camera, start, max_distance=max_distance, strides=(2, 1),
                    iterations=(10, 10), depth_max=depth_max, **colors)
    best.iterations += coarse.iterations
    if not best.passes(min_fitness, max_rmse) and global_fallback:
        g = global_registration(source_depth, target_depth, camera, voxel=voxel, depth_max=depth_max)
        if g.success:
            alt = icp_rgbd(source_depth, target_depth, camera, g.T_target_source, max_distance=max_distance,
                           depth_max=depth_max, **colors)
            if alt.success and (not best.success or alt.fitness > best.fitness):
                alt.method = "register_rgbd/global"
                best = alt
    if best.success and not best.passes(min_fitness, max_rmse):
        return RegistrationResult.failure(T0, POOR_ALIGNMENT, "register_rgbd", fitness=best.fitness,
                                          inlier_rmse=best.inlier_rmse, information=best.information,
                                          iterations=best.iterations, n_correspondences=best.n_correspondences)
    if not best.success:
        best.T_target_source = T0.copy()
    best.method = best.method if best.method.startswith("register_rgbd") else "register_rgbd"
    return best
