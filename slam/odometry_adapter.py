"""The one place the agent calls RGB-D registration: frame-to-frame coarse odometry (tracking, eq. 4) and the
loop-closure registration (coarse eq. 7, then point-to-plane ICP eq. 8).

Interim implementation on Open3D (`compute_rgbd_odometry`, `registration_icp`) until `registration.rgbd` /
`registration.icp` land; the swap is confined to `_coarse` and `_icp` below.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .frames import RGBD

_TERM = "hybrid"  # the paper's hybrid colour-depth term; "color" is the colour-only term


@dataclass
class Registration:
    T_target_source: np.ndarray  # [4, 4] maps source-camera points into the target camera
    success: bool
    reason: str = ""
    fitness: float = 0.0
    inlier_rmse: float = float("inf")
    information: np.ndarray = field(default_factory=lambda: np.eye(6))  # [6, 6], twist order [omega, v]


def _o3d_rgbd(f: RGBD, max_depth: float):
    import open3d as o3d

    color = o3d.geometry.Image(np.ascontiguousarray(f.color))
    depth = o3d.geometry.Image(np.ascontiguousarray(f.depth.astype(np.float32)))
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, depth, depth_scale=1.0, depth_trunc=max_depth, convert_rgb_to_intensity=True)


def _intrinsic(f: RGBD):
    import open3d as o3d

    c = f.camera
    return o3d.camera.PinholeCameraIntrinsic(int(c.width), int(c.height), c.fx, c.fy, c.cx, c.cy)


def _coarse(source: RGBD, target: RGBD, init: np.ndarray, max_depth: float) -> Registration:
    import open3d as o3d

    opt = o3d.pipelines.odometry.OdometryOption()
    opt.depth_max = float(max_depth)
    opt.depth_diff_max = 0.07
    ok, T, info = o3d.pipelines.odometry.compute_rgbd_odometry(
        _o3d_rgbd(source, max_depth), _o3d_rgbd(target, max_depth), _intrinsic(source), np.asarray(init, np.float64),
        (o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm() if _TERM == "color" else o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()), opt)
    T = np.asarray(T, dtype=np.float64)
    if not ok or not np.all(np.isfinite(T)):
        return Registration(np.asarray(init, np.float64), False, "coarse odometry did not converge")
    return Registration(T, True, information=np.asarray(info, dtype=np.float64))


def coarse_odometry(source: RGBD, target: RGBD, init: np.ndarray | None = None, *, max_depth: float = 10.0) -> Registration:
    """Hybrid colour-depth RGB-D odometry: T_target_source between two frames of the same camera model."""
    return _coarse(source, target, np.eye(4) if init is None else init, max_depth)


def _cloud(f: RGBD, max_depth: float, voxel: float):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud.create_from_rgbd_image(_o3d_rgbd(f, max_depth), _intrinsic(f))
    if voxel > 0:
        pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * max(voxel, 0.01), max_nn=30))
    return pcd


def _icp(source: RGBD, target: RGBD, init: np.ndarray, *, max_distance: float, max_depth: float) -> Registration:
    import open3d as o3d

    voxel = max_distance / 2.0
    src, tgt = _cloud(source, max_depth, voxel), _cloud(target, max_depth, voxel)
    if len(src.points) < 50 or len(tgt.points) < 50:
        return Registration(init, False, f"too few points ({len(src.points)}, {len(tgt.points)})")
    reg = o3d.pipelines.registration
    res = reg.registration_icp(src, tgt, max_distance, np.asarray(init, np.float64),
                               reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=30))
    T = np.asarray(res.transformation, dtype=np.float64)
    info = np.asarray(reg.get_information_matrix_from_point_clouds(src, tgt, max_distance, T), dtype=np.float64)
    return Registration(T, True, "", float(res.fitness), float(res.inlier_rmse) if res.fitness > 0 else float("inf"), info)


def register_loop(source: RGBD, target: RGBD, init: np.ndarray, *, max_distance: float,
                  max_depth: float = 10.0) -> Registration:
    """Loop-closure registration: coarse RGB-D alignment from `init`, then point-to-plane ICP.

    Gates (fitness, RMSE) are applied by the caller; `success` only says the registration could run."""
    coarse = _coarse(source, target, init, max_depth)
    start = coarse.T_target_source if coarse.success else np.asarray(init, np.float64)
    fine = _icp(source, target, start, max_distance=max_distance, max_depth=max_depth)
    if not coarse.success and fine.success:
        fine.reason = "coarse stage failed; ICP from the tracked initial guess"
    return fine
