"""The one place the agent calls RGB-D registration: frame-to-frame coarse odometry (tracking, eq. 4) and the
loop-closure registration (coarse eq. 7, then point-to-plane ICP eq. 8), both from `registration.rgbd`.

The agent only sees `Registration` (a view of `registration.result.RegistrationResult`), so another registration
back-end can be swapped in here without touching the tracker or the loop closer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels import se3

from .frames import RGBD


@dataclass
class Registration:
    T_target_source: np.ndarray  # [4, 4] maps source-camera points into the target camera
    success: bool
    reason: str = ""
    fitness: float = 0.0
    inlier_rmse: float = float("inf")
    information: np.ndarray = field(default_factory=lambda: np.eye(6))  # [6, 6], twist order [omega, v]
    n_correspondences: int = 0


# The nearest rigid transform: the registration checks its initial guess strictly.
rigid = se3.project_rigid


def _view(r) -> Registration:
    ok = bool(r.success)
    return Registration(np.asarray(r.T_target_source, dtype=np.float64), ok, "" if ok else str(r.reason),
                        float(r.fitness), float(r.inlier_rmse) if r.fitness > 0 else float("inf"),
                        np.asarray(r.information, dtype=np.float64), int(r.n_correspondences))


def coarse_odometry(source: RGBD, target: RGBD, init: np.ndarray | None = None, *, max_depth: float = 10.0,
                    pyramids: tuple | None = None, eval_stride: int = 1) -> Registration:
    """Hybrid colour-depth RGB-D odometry (projective point-to-plane + intensity over a pyramid):
    T_target_source between two frames of the same camera. `pyramids`: the frames' FramePyramid (`pyramid`),
    whose levels are kept for their next registration."""
    from swarmsplat.registration.icp import default_strides
    from swarmsplat.registration.rgbd import rgbd_odometry

    kw = {}
    if source.camera.width <= 200:
        # Small frames: registration's default pyramid drops its finest level and keeps only one (80 px), too
        # little to converge on a few-cm step; use every level down to 40 px, including the finest.
        strides = default_strides(source.camera.width, 40)
        kw = dict(strides=strides, iterations=[15] * len(strides))
    r = rgbd_odometry(source.color, source.depth, target.color, target.depth, source.camera,
                      np.eye(4) if init is None else rigid(init), method="hybrid", depth_max=max_depth,
                      pyramids=pyramids, eval_stride=eval_stride, **kw)
    return _view(r)


def pyramid(frame: RGBD):
    """The registration.pyramid.FramePyramid of `frame` on the active kernel device: pass one per frame to
    `coarse_odometry` and the tracker's refinement so each level is computed once."""
    from swarmsplat import kernels
    from swarmsplat.registration.pyramid import FramePyramid

    return FramePyramid(frame.depth, frame.color, frame.camera, kernels.active().torch_device)


def register_loop(source: RGBD, target: RGBD, init: np.ndarray, *, max_distance: float, min_fitness: float,
                  max_rmse: float, max_depth: float = 10.0, global_fallback: bool = True) -> Registration:
    """Loop-closure registration from `init`: coarse RGB-D odometry, then point-to-plane ICP (with a global
    FPFH + RANSAC restart when the result fails the fitness / RMSE gate and `global_fallback` is set). The caller applies the gates again to
    record why a candidate was rejected; fitness and RMSE are filled in even on failure."""
    from swarmsplat.registration.rgbd import register_rgbd

    r = register_rgbd(source.color, source.depth, target.color, target.depth, source.camera, rigid(init),
                      max_distance=max_distance, min_fitness=min_fitness, max_rmse=max_rmse, depth_max=max_depth,
                      global_fallback=global_fallback)
    return _view(r)
