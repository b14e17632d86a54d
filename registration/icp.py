"""Point-to-plane ICP (paper eq. 8) on the kernels: coarse-to-fine projective ICP for organised RGB-D frames and
nearest-neighbour ICP for unorganised clouds, returning a RegistrationResult with Open3D's fitness / RMSE.

Both minimise sum_i w_i (n_i . (T p_i - q_i))^2 over T_target_source by Gauss-Newton on a left twist
[omega, v]; each step is one association kernel and one reduction kernel on the active backend
(`kernels.use(...)`), and a 6x6 solve here in float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from swarmsplat import kernels
from swarmsplat.kernels import icp as K
from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError

from .pointcloud import check_camera, check_color, check_depth, check_points, check_pose, level_camera, select_rows
from .pyramid import FramePyramid
from .result import DEGENERATE, NOT_CONVERGED, OK, TOO_FEW_POINTS, RegistrationResult


def solve_step(ne: K.NormalEquations) -> np.ndarray:
    """Gauss-Newton step xi [6] = -(JtJ)^-1 Jtr, with a tiny Levenberg damping so a rank-deficient system
    (a plane) moves only along the directions it constrains instead of exploding."""
    H = ne.JtJ.numpy()
    damp = 1e-9 * max(np.trace(H), 1e-12) / 6.0
    return np.linalg.solve(H + damp * np.eye(6), -ne.Jtr.numpy())


def geometry_check(p: torch.Tensor, q: torch.Tensor, n: torch.Tensor) -> tuple[np.ndarray, float]:
    """Information matrix (Open3D convention, at target points q) and a degeneracy score for correspondences.

    p, q, n [K, 3]: transformed source points, target points, target normals. The score is the smallest over the
    largest eigenvalue of the point-to-plane JᵀJ taken about the correspondences' centroid, with rotation
    columns scaled by their RMS lever arm: ~0 for a plane (3 free directions) or a corridor (1), O(0.1) for a room.
    """
    p, q, n = p.double(), q.double(), n.double()
    Kc = p.shape[0]
    # G = [-[q]x, I] per correspondence (the rows of Open3D's get_information_matrix_from_point_clouds), so
    # sum G^T G = [[sum(|q|^2 I - q q^T), [sum q]x], [-[sum q]x, K I]].
    qs = q.sum(0).numpy()
    info = np.zeros((6, 6))
    info[:3, :3] = float((q * q).sum()) * np.eye(3) - (q.T @ q).numpy()
    info[:3, 3:] = se3.hat(qs)
    info[3:, :3] = -se3.hat(qs)
    info[3:, 3:] = Kc * np.eye(3)
    c = p.mean(0, keepdim=True)
    lever = float(torch.sqrt(((p - c) ** 2).sum(1).mean()).clamp_min(1e-9))
    J = torch.cat([torch.cross(p - c, n, dim=1) / lever, n], 1)
    ev = np.linalg.eigvalsh((J.T @ J).numpy() / max(Kc, 1))
    return info, float(ev[0] / max(ev[-1], 1e-300))


def default_strides(width: int, coarsest_width: int = 80) -> list[int]:
    """Pyramid strides: powers of two from the largest <= 8 keeping the coarsest level >= `coarsest_width`
    pixels wide, down to 1 (640 -> [8, 4, 2, 1], 320 -> [4, 2, 1], 160 -> [2, 1])."""
    top = 8
    while top > 1 and width / top < coarsest_width:
        top //= 2
    return [top >> k for k in range(top.bit_length())]


@dataclass
class _Level:
    cam: PinholeCamera
    src: torch.Tensor  # [N, 3] valid source points (source frame)
    src_n: torch.Tensor  # [N, 3] their normals (0 where unknown)
    tv: torch.Tensor  # [h, w, 3] target vertices
    tn: torch.Tensor  # [h, w, 3] target normals
    photo: K.PhotometricTerm | None


def _level(sp: FramePyramid, tp: FramePyramid, stride, jump, depth_max, photometric_weight) -> _Level:
    lc = level_camera(sp.camera, stride)
    src, src_n, sil = sp.points(stride, depth_max, jump)
    tv, tn = tp.maps(stride, depth_max, jump)
    photo = None
    if sil is not None and tp.color is not None and photometric_weight > 0:
        photo = K.PhotometricTerm(sil, tp.smoothed(stride), tp.gradient(stride), lc, float(photometric_weight))
    return _Level(lc, src, src_n, tv, tn, photo)


def _t(T: np.ndarray, dev) -> torch.Tensor:
    return torch.from_numpy(T.astype(np.float32)).to(dev)


def icp_rgbd(source_depth: np.ndarray, target_depth: np.ndarray, camera: PinholeCamera,  # [H, W] metres each
             init: np.ndarray = np.eye(4), *,
             source_color: np.ndarray | None = None, target_color: np.ndarray | None = None,  # [H, W, 3] uint8
             max_distance: float = 0.05, strides: Sequence[int] | None = None, iterations: Sequence[int] | None = None,
             gates: Sequence[float] | None = None, max_angle_deg: float = 45.0, max_depth_jump: float = 0.05,
             depth_max: float | None = None,
             robust: str = "huber", robust_scale: float | None = None, photometric_weight: float = 0.0,
             min_points: int = 100, min_correspondences: int = 100, degenerate_ratio: float = 1e-3,
             tolerance: tuple[float, float] = (1e-5, 1e-5),
             pyramids: tuple[FramePyramid, FramePyramid] | None = None,
             eval_stride: int = 1) -> RegistrationResult:
    """Coarse-to-fine projective point-to-plane ICP between two organised depth frames.

    Levels take every s-th pixel for s in `strides` (default: powers of two from the largest <= 8 that keeps the
    coarsest level >= 80 pixels wide, down to 1), with `iterations[k]` Gauss-Newton steps each (default 10) and a
    distance gate `gates[k]` (default `max_distance * s` metres, wider while coarse); correspondences need a
    normal angle below `max_angle_deg`. Geometry alone has a narrow basin in box-like scenes (measured on the
    synthetic room: 5 cm / 3 deg from identity can slide along walls); start it from a coarse estimate
    (`registration.rgbd.rgbd_odometry`) or add the colour term, which converged from 19 cm / 10 deg.
    robust: "none" | "huber" | "tukey" with `robust_scale` metres (default half the level's gate). With both
    colours and `photometric_weight` > 0 an intensity term (hybrid alignment) is added.
    Steps stop when |omega| and |v| fall below `tolerance` (rad, m). fitness / inlier_rmse are evaluated at full
    resolution (every `eval_stride`-th source pixel) with projective correspondences within `max_distance` and
    Open3D's definitions.
    `pyramids` (source, target): the frames' FramePyramid (registration.pyramid) of these same depths and colours,
    whose levels are kept for the next registration of either frame; made here when None.
    """
    camera = check_camera(camera)
    sd = check_depth("source_depth", source_depth, camera)
    td = check_depth("target_depth", target_depth, camera)
    T0 = check_pose("init", init)
    if (source_color is None) != (target_color is None):
        raise InputError("arguments 'source_color' and 'target_color': give both or neither")
    strides = default_strides(camera.width) if strides is None else strides
    if iterations is None:
        iterations = [10] * len(strides)
    if len(strides) != len(iterations) or not strides or any(int(s) < 1 for s in strides):
        raise InputError(f"arguments 'strides'/'iterations': expected equal-length lists of positive ints, got "
                         f"{list(strides)} and {list(iterations)}")
    if gates is not None and len(gates) != len(strides):
        raise InputError(f"argument 'gates': expected one gate per level ({len(strides)}), got {len(gates)}")
    if not max_distance > 0:
        raise InputError(f"argument 'max_distance': expected > 0 metres, got {max_distance}")
    method = "icp_rgbd"
    n_src = int(((sd > 0) & (sd < (depth_max or np.inf))).sum())
    n_tgt = int(((td > 0) & (td < (depth_max or np.inf))).sum())
    if min(n_src, n_tgt) < min_points:
        return RegistrationResult.failure(T0, TOO_FEW_POINTS, method)
    dev = kernels.active().torch_device
    if source_color is not None:
        source_color = check_color("source_color", source_color, camera)
        target_color = check_color("target_color", target_color, camera)
    sp, tp = pyramids or (FramePyramid(sd, source_color, camera, dev), FramePyramid(td, target_color, camera, dev))

    T = T0.copy()
    total_iters, converged = 0, False
    for li, (stride, n_it) in enumerate(zip(strides, iterations)):
        lv = _level(sp, tp, int(stride), max_depth_jump, depth_max, photometric_weight)
        gate = float(gates[li]) if gates is not None else max_distance * stride
        k = robust_scale if robust_scale is not None else 0.5 * gate
        converged = False
        for _ in range(int(n_it)):
            ne = K.projective_normal_equations(lv.src, _t(T, dev), lv.tv, lv.tn, lv.cam, max_distance=gate,
                                               source_normals=lv.src_n, max_angle_deg=max_angle_deg, robust=robust,
                                               robust_scale=k if robust != "none" else 0.0, photometric=lv.photo,
                                               validate=False)
            if ne.count < min(min_correspondences, max(6, lv.src.shape[0] // 10)):
                if li == len(strides) - 1 or ne.count < 6:
                    return RegistrationResult.failure(T0, TOO_FEW_POINTS, method, iterations=total_iters,
                                                      n_correspondences=ne.count)
                break  # too coarse to say; try the next level
            xi = solve_step(ne)
            T = se3.exp(xi) @ T
            total_iters += 1
            if np.linalg.norm(xi[:3]) < tolerance[0] and np.linalg.norm(xi[3:]) < tolerance[1]:
                converged = True
                break
        last_step = xi if total_iters else np.zeros(6)

    # Final evaluation at full resolution: Open3D's fitness / RMSE, information matrix, degeneracy.
    # eval_stride > 1 scores every s-th source pixel against the whole target, so RMSE and fitness keep their scale.
    src = sp.points(int(eval_stride), depth_max, max_depth_jump)[0]
    tv, tn = tp.maps(1, depth_max, max_depth_jump)
    idx = K.associate_projective(src, _t(T, dev), tv, tn, camera, max_distance=max_distance, validate=False)
    n_eval = n_src if eval_stride == 1 else int(src.shape[0])
    return _finish(T, T0, src, tv.reshape(-1, 3), tn.reshape(-1, 3), idx, n_eval, total_iters,
                   converged or np.linalg.norm(last_step[:3]) < 1e-4 and np.linalg.norm(last_step[3:]) < 1e-4,
                   min_correspondences, degenerate_ratio, method)


def evaluate_rgbd(source_depth: np.ndarray, target_depth: np.ndarray, camera: PinholeCamera,  # [H, W] metres
                  T_target_source: np.ndarray, *, max_distance: float = 0.05, max_depth_jump: float = 0.05,
                  depth_max: float | None = None, min_correspondences: int = 100, degenerate_ratio: float = 1e-3,
                  method: str = "evaluate_rgbd") -> RegistrationResult:
    """Score a given pose with the same evaluation as `icp_rgbd` (projective correspondences within
    `max_distance` at full resolution, Open3D's fitness / RMSE / information) without moving it."""
    camera = check_camera(camera)
    sd = check_depth("source_depth", source_depth, camera)
    td = check_depth("target_depth", target_depth, camera)
    T = check_pose("T_target_source", T_target_source)
    dev = kernels.active().torch_device
    n_src = int(((sd > 0) & (sd < (depth_max or np.inf))).sum())
    lv = _level(FramePyramid(sd, None, camera, dev), FramePyramid(td, None, camera, dev), 1, max_depth_jump,
                depth_max, 0.0)
    idx = K.associate_projective(lv.src, _t(T, dev), lv.tv, lv.tn, lv.cam, max_distance=max_distance, validate=False)
    return _finish(T, T, lv.src, lv.tv.reshape(-1, 3), lv.tn.reshape(-1, 3), idx, n_src, 0, True,
                   min_correspondences, degenerate_ratio, method)


def _finish(T, T0, src, tp, tn, idx, n_src, iters, converged, min_corr, degenerate_ratio, method) -> RegistrationResult:
    m = idx >= 0
    count = int(m.sum())
    if count < min_corr:
        return RegistrationResult.failure(T0, TOO_FEW_POINTS, method, iterations=iters, n_correspondences=count)
    Tt = torch.from_numpy(T).to(src.device)
    src_m, idx_m = select_rows(m, src, idx)
    idx_m = idx_m.long()
    p = src_m.double() @ Tt[:3, :3].T + Tt[:3, 3]
    q, n = tp.index_select(0, idx_m).double(), tn.index_select(0, idx_m).double()
    fitness = count / max(n_src, 1)
    rmse = float(torch.sqrt(((p - q) ** 2).sum(1).mean()))
    info, ratio = geometry_check(p.cpu(), q.cpu(), n.cpu())
    stats = dict(fitness=fitness, inlier_rmse=rmse, information=info, iterations=iters, n_correspondences=count)
    if ratio < degenerate_ratio:
        return RegistrationResult.failure(T0, DEGENERATE, method, **stats)
    if not converged:
        return RegistrationResult.failure(T0, NOT_CONVERGED, method, **stats)
    return RegistrationResult(T, True, OK, method=method, **stats)


def icp_clouds(source_points: np.ndarray, target_points: np.ndarray, init: np.ndarray = np.eye(4), *,  # [N,3] [M,3]
               max_distance: float, target_normals: np.ndarray | None = None, normal_radius: float | None = None,
               max_iterations: int = 30, relative_fitness: float = 1e-6, relative_rmse: float = 1e-6,
               robust: str = "none", robust_scale: float = 0.0, min_points: int = 30, min_correspondences: int = 30,
               degenerate_ratio: float = 1e-3) -> RegistrationResult:
    """Point-to-plane ICP between unorganised clouds with Open3D's `registration_icp` policy.

    Correspondence: the nearest target point within `max_distance` metres of T p (grid search, exact). Each
    iteration takes a Gauss-Newton step on all correspondences, re-associates, and stops when both fitness and
    inlier RMSE change by less than `relative_fitness` / `relative_rmse` (absolute changes, as Open3D), or after
    `max_iterations`. target_normals [M, 3] are used as given; when None they are estimated from neighbours
    within `normal_radius` (default 2 * max_distance), oriented towards the origin of the target frame.
    """
    src_np = check_points("source_points", source_points)
    tgt_np = check_points("target_points", target_points)
    T0 = check_pose("init", init)
    if not max_distance > 0:
        raise InputError(f"argument 'max_distance': expected > 0 metres, got {max_distance}")
    method = "icp_clouds"
    if min(len(src_np), len(tgt_np)) < min_points:
        return RegistrationResult.failure(T0, TOO_FEW_POINTS, method)
    dev = kernels.active().torch_device
    src = torch.from_numpy(src_np).to(dev)
    tgt = torch.from_numpy(tgt_np).to(dev)
    grid = K.PointGrid(tgt, max_distance)
    if target_normals is not None:
        tn_np = check_points("target_normals", target_normals)
        if tn_np.shape != tgt_np.shape:
            raise InputError(f"argument 'target_normals': expected shape {list(tgt_np.shape)}, got {list(tn_np.shape)}")
        tn = torch.from_numpy(tn_np).to(dev)
    else:
        r = normal_radius or 2.0 * max_distance
        ngrid = grid if abs(r - max_distance) < 1e-12 else K.PointGrid(tgt, r)
        tn = K.cloud_normals(tgt, r, viewpoint=(0.0, 0.0, 0.0), grid=ngrid)

    def step(T):
        idx = K.associate_nearest(src, _t(T, dev), grid, max_distance=max_distance, validate=False)
        ne = K.reduce_point_to_plane(src, _t(T, dev), tgt, tn, idx, robust=robust, robust_scale=robust_scale,
                                     validate=False)
        rmse = np.sqrt(ne.dist_sq / ne.count) if ne.count else 0.0
        return idx, ne, ne.count / len(src_np), rmse

    T = T0.copy()
    idx, ne, fit, rmse = step(T)
    converged, iters, xi = False, 0, np.zeros(6)
    for _ in range(int(max_iterations)):
        if ne.count < 6:
            break
        xi = solve_step(ne)
        T = se3.exp(xi) @ T
        iters += 1
        idx, ne, fit_new, rmse_new = step(T)
        done = abs(fit - fit_new) < relative_fitness and abs(rmse - rmse_new) < relative_rmse
        fit, rmse = fit_new, rmse_new
        if done:
            converged = True
            break
    converged = converged or (np.linalg.norm(xi[:3]) < 1e-4 and np.linalg.norm(xi[3:]) < 1e-4)
    return _finish(T, T0, src, tgt, tn, idx, len(src_np), iters, converged, min_correspondences, degenerate_ratio,
                   method)
