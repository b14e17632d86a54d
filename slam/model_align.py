"""Frame-to-model Gauss-Newton (the tracker's refinement stage) on the ICP kernels, with the model side prepared
once per model view instead of once per frame.

The model view (slam.tracker.model_view: the active submap rendered as colour + alpha-weighted depth at the last
keyframe's pose) is the target: its vertices, normals, intensity and intensity gradient per pyramid level are
computed when the view is rendered (`ModelTarget`) and reused by every frame aligned to it. Each frame costs its
own source level and the Gauss-Newton steps: projective point-to-plane + intensity residuals (the hybrid
objective of registration.icp.icp_rgbd, same gates, Huber weights, normal-angle gate), the twist applied on
the left in the view's camera frame. No full-resolution evaluation or information matrix: the refined pose only
replaces the coarse one, whose registration still feeds the pose graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from kernels import icp as K
from kernels import se3
from registration.icp import solve_step
from registration.pointcloud import gradient, intensity, level_camera, smooth_and_stride

from .frames import RGBD

MAX_DEPTH_JUMP = 0.05  # m, normals are not estimated across larger depth steps (as registration.icp)
MAX_ANGLE_DEG = 45.0


@dataclass
class _TargetLevel:
    stride: int
    cam: object  # PinholeCamera of the level
    vertices: torch.Tensor  # [h, w, 3] view-camera frame
    normals: torch.Tensor  # [h, w, 3]
    intensity: torch.Tensor  # [h, w] in [0, 1]
    gradient: torch.Tensor  # [h, w, 2]


def _depth_level(depth: np.ndarray, stride: int, max_depth: float) -> torch.Tensor:
    d = torch.from_numpy(np.ascontiguousarray(depth[::stride, ::stride], dtype=np.float32))
    return torch.where(d < max_depth, d, torch.zeros_like(d))


class ModelTarget:
    """The target side of the alignment, per stride in `strides` (coarsest first), from one model view."""

    def __init__(self, view: RGBD, strides: list[int], *, max_depth: float = 10.0):
        self.camera = view.camera
        self.valid_fraction = view.valid_fraction()
        gray = torch.from_numpy(intensity(view.color))
        self.levels = []
        for s in strides:
            lc = level_camera(view.camera, s)
            tv, tn = K.vertices_normals_from_depth(_depth_level(view.depth, s, max_depth), lc, MAX_DEPTH_JUMP)
            ti = smooth_and_stride(gray, s)
            self.levels.append(_TargetLevel(s, lc, tv, tn, ti, gradient(ti).contiguous()))


@dataclass
class AlignResult:
    T_view_cam: np.ndarray  # [4, 4] maps frame-camera points into the view camera
    success: bool
    iterations: int
    count: int  # correspondences of the last step
    rmse: float  # point-to-plane RMS residual of the last step (m)


def align_to_model(frame: RGBD, target: ModelTarget, T_view_cam: np.ndarray, *, iterations: int,
                   photometric_weight: float, max_distance: float, max_depth: float = 10.0,
                   min_correspondences: int = 100, tolerance: float = 1e-5) -> AlignResult:
    """Gauss-Newton of `frame` (the same camera as the view) onto `target` from T_view_cam [4, 4]; `iterations`
    steps per level, correspondence gate max_distance x stride (m). Fails (returning the start pose) when a
    level has fewer than `min_correspondences` correspondences."""
    if frame.camera != target.camera:
        raise ValueError("align_to_model: the frame must have the model view's camera")
    T = np.asarray(T_view_cam, dtype=np.float64).copy()
    T0, total, ne = T.copy(), 0, None
    gray = torch.from_numpy(intensity(frame.color))
    for lv in target.levels:
        d = _depth_level(frame.depth, lv.stride, max_depth)
        sv, sn = K.vertices_normals_from_depth(d, lv.cam, MAX_DEPTH_JUMP)
        m = (d > 0).reshape(-1)
        src, src_n = sv.reshape(-1, 3)[m].contiguous(), sn.reshape(-1, 3)[m].contiguous()
        photo = None
        if photometric_weight > 0:
            si = smooth_and_stride(gray, lv.stride).reshape(-1)[m].contiguous()
            photo = K.PhotometricTerm(si, lv.intensity, lv.gradient, lv.cam, float(photometric_weight))
        gate = max_distance * lv.stride
        for _ in range(iterations):
            ne = K.projective_normal_equations(src, torch.from_numpy(T.astype(np.float32)), lv.vertices, lv.normals,
                                               lv.cam, max_distance=gate, source_normals=src_n,
                                               max_angle_deg=MAX_ANGLE_DEG, robust="huber", robust_scale=0.5 * gate,
                                               photometric=photo, validate=False)
            if ne.count < min_correspondences:
                return AlignResult(T0, False, total, ne.count, float("nan"))
            xi = solve_step(ne)
            T = se3.exp(xi) @ T
            total += 1
            if np.linalg.norm(xi[:3]) < tolerance and np.linalg.norm(xi[3:]) < tolerance:
                break
    rmse = float(np.sqrt(ne.cost / max(ne.count, 1))) if ne is not None else float("nan")
    return AlignResult(T, True, total, ne.count if ne is not None else 0, rmse)
