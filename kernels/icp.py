"""Dense ICP kernels: normals, data association and one-pass point-to-plane normal equations.

Conventions
- Points are float32 torch tensors on the active device. `T_target_source` [4, 4] maps source-frame points into
  the target frame (float32 or float64; used in float32 inside the kernels).
- An association is an int32 [N] tensor: for each source point the index of its target point in the flattened
  target array (`v * W + u` for an organised [H, W, 3] vertex map), or -1 for none.
- The point-to-plane residual is r = n_q . (T p - q). Its Jacobian is taken wrt a left twist xi = [omega, v]
  (rotation first, as `kernels.se3`): T <- exp(xi) T, so J = [p' x n, n] with p' = T p.
- Reductions run in one pass: every block of points accumulates in float64 registers and writes one row of a
  [B, 48] partial-sum table, which torch sums. No atomics; deterministic for a fixed block count.

Backends: `kernels/_warp/icp.py` (wp.HashGrid for neighbours) and `kernels/_taichi/icp.py` (a uniform hash grid
built with torch), twins in `kernels/_ref_icp.py`. On the CPU, Taichi runs each kernel's outer loop on every core;
Warp runs a launch on one thread, so its wrapper cuts every launch into one part per core, each launched from its
own Python thread (Warp releases the GIL during a launch; parts write disjoint outputs, results are bitwise those
of one launch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .backend import active
from .camera import PinholeCamera
from .checks import check_tensor
from .errors import InputError

ROBUST_KINDS = {"none": 0, "huber": 1, "tukey": 2}
N_SLOTS = 48


def _be():
    import importlib

    b = active()
    return b, importlib.import_module(f"{__package__}._{b.name}.icp")


def _pose(name: str, T, device) -> torch.Tensor:
    if not isinstance(T, torch.Tensor):
        T = torch.as_tensor(T)
    _check(name, T, (4, 4), dtypes=(torch.float32, torch.float64))
    return T.to(device=device, dtype=torch.float32).contiguous()


def _finite(name: str, x: torch.Tensor) -> torch.Tensor:
    # One reduction instead of an elementwise isfinite mask: NaN and Inf propagate into the sum, and it is ~100x
    # cheaper on a busy CPU (only sums beyond 3e38 would be a false alarm, and such inputs are not metres).
    if x.numel() and not bool(torch.isfinite(x.sum())):
        raise InputError(f"argument '{name}': contains NaN or Inf")
    return x


def _check(name: str, x, shape, dtypes=(torch.float32,), device=None, validate: bool = True) -> torch.Tensor:
    check_tensor(name, x, shape, dtypes=dtypes, device=device, finite=False)
    return _finite(name, x) if validate and x.is_floating_point() else x


def _points(name: str, x: torch.Tensor, device, validate: bool = True) -> torch.Tensor:
    return _check(name, x, (None, 3), device=device, validate=validate).contiguous()


@dataclass(frozen=True)
class NormalEquations:
    """Sums over the associated points of one ICP step (float64, CPU).

    JtJ [6, 6] and Jtr [6] are the weighted Gauss-Newton system (twist [omega, v]); the step is
    xi = -solve(JtJ, Jtr). `cost` = sum w r^2 (point-to-plane), `dist_sq` = sum |p' - q|^2 (Euclidean, for
    Open3D's inlier RMSE), `count` = associated points, `photo_cost` / `photo_count` the photometric term's
    share, `abs_residual` = sum |r| (unweighted).
    """

    JtJ: torch.Tensor
    Jtr: torch.Tensor
    cost: float
    dist_sq: float
    count: int
    photo_cost: float
    photo_count: int
    abs_residual: float

    @classmethod
    def from_sums(cls, s: torch.Tensor) -> "NormalEquations":
        s = s.detach().to("cpu", torch.float64)
        v = s.tolist()  # one conversion instead of one per scalar (this runs once per ICP iteration)
        return cls(s[0:36].reshape(6, 6).clone(), s[36:42].clone(), v[42], v[43], int(round(v[44])), v[45],
                   int(round(v[46])), v[47])


@dataclass(frozen=True)
class PhotometricTerm:
    """Optional photometric residual for projective association (hybrid colour-depth alignment).

    source_intensity [N] float32 in [0, 1], one per source point; target_intensity [H, W] float32;
    target_gradient [H, W, 2] float32 (dI/du, dI/dv per pixel); camera of the target image; `weight` scales
    both the residual and its Jacobian (so its squared weight multiplies the photometric cost).
    """

    source_intensity: torch.Tensor
    target_intensity: torch.Tensor
    target_gradient: torch.Tensor
    camera: PinholeCamera
    weight: float


class PointGrid:
    """A neighbour-search structure over a fixed set of target points (build once, query many times).

    points [M, 3] float32; `cell_size` in metres (queries are exact for any radius, fastest near cell_size).
    Warp: wp.HashGrid; Taichi: a uniform grid hashed into a table built with torch.
    """

    def __init__(self, points: torch.Tensor, cell_size: float):
        b, mod = _be()
        self.points = _points("points", points, b.torch_device)
        if not (cell_size > 0 and torch.isfinite(torch.tensor(cell_size))):
            raise InputError(f"argument 'cell_size': expected a positive finite size in metres, got {cell_size}")
        self.cell_size = float(cell_size)
        self.backend = b
        self._impl = mod.build_grid(self.points, self.cell_size, b.device)


def vertices_normals_from_depth(depth: torch.Tensor, camera: PinholeCamera,  # [H, W] metres, 0 = invalid
                                max_depth_jump: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Organised depth -> (vertices [H, W, 3], normals [H, W, 3]) float32 in the camera frame.

    Normals from central differences; 0 where a 4-neighbour is invalid or differs by more than
    `max_depth_jump * depth` (a depth discontinuity). Normals point towards the camera.
    """
    b, mod = _be()
    _check("depth", depth, (camera.height, camera.width), dtypes=(torch.float32,), device=b.torch_device)
    return mod.vertices_normals(depth.contiguous(), camera, float(max_depth_jump), b.device)


def cloud_moments(grid: PointGrid, queries: torch.Tensor, radius: float) -> torch.Tensor:  # [Q, 3] -> [Q, 10]
    """Per query: count, sum and sum of outer products of the grid points within `radius` (float64 [Q, 10]:
    n, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz)."""
    b, mod = _be()
    queries = _points("queries", queries, b.torch_device)
    if not radius > 0:
        raise InputError(f"argument 'radius': expected > 0, got {radius}")
    return mod.cloud_moments(grid._impl, grid.points, queries, float(radius), b.device)


def normals_from_moments(moments: torch.Tensor, points: torch.Tensor,  # [Q, 10], [Q, 3]
                         viewpoint=None, min_neighbors: int = 3) -> torch.Tensor:
    """Smallest-eigenvector normals [Q, 3] float32 of the neighbour covariance; oriented towards `viewpoint`
    (3 floats, same frame) when given; 0 where fewer than `min_neighbors` neighbours."""
    m = moments.to(torch.float64)
    n = m[:, 0:1].clamp_min(1.0)
    mean = m[:, 1:4] / n
    C = torch.empty(m.shape[0], 3, 3, dtype=torch.float64, device=m.device)
    for a, bb, k in ((0, 0, 4), (0, 1, 5), (0, 2, 6), (1, 1, 7), (1, 2, 8), (2, 2, 9)):
        C[:, a, bb] = C[:, bb, a] = m[:, k] / n[:, 0] - mean[:, a] * mean[:, bb]
    normals = torch.linalg.eigh(C)[1][:, :, 0]
    if viewpoint is not None:
        vp = torch.as_tensor(viewpoint, dtype=torch.float64, device=m.device).reshape(1, 3)
        flip = ((vp - points.to(torch.float64)) * normals).sum(1) < 0
        normals[flip] *= -1.0
    normals[m[:, 0] < min_neighbors] = 0.0
    return normals.to(torch.float32)


def cloud_normals(points: torch.Tensor, radius: float, *, viewpoint=None, min_neighbors: int = 3,
                  grid: PointGrid | None = None) -> torch.Tensor:  # [N, 3] -> [N, 3]
    """Normals of an unorganised cloud from all neighbours within `radius` (PCA), found through a grid."""
    grid = grid if grid is not None else PointGrid(points, radius)
    return normals_from_moments(cloud_moments(grid, points, radius), points, viewpoint, min_neighbors)


def associate_projective(source_points: torch.Tensor, T_target_source,  # [N, 3], [4, 4]
                         target_vertices: torch.Tensor, target_normals: torch.Tensor,  # [H, W, 3] each
                         camera: PinholeCamera, *, max_distance: float,
                         source_normals: torch.Tensor | None = None, max_angle_deg: float | None = None,
                         validate: bool = True) -> torch.Tensor:
    """Projective association for organised frames -> int32 [N] flat target pixel index or -1.

    p' = T p projects to the nearest target pixel; kept when inside the image, the target normal is valid,
    |p' - q| <= max_distance (metres) and, with source normals and `max_angle_deg`, angle(R n_s, n_q) <= max.
    Source points with z <= 0 are treated as invalid.
    """
    b, mod = _be()
    dev = b.torch_device
    source_points = _points("source_points", source_points, dev, validate)
    H, W = camera.height, camera.width
    _check("target_vertices", target_vertices, (H, W, 3), device=dev, validate=validate)
    _check("target_normals", target_normals, (H, W, 3), device=dev, validate=validate)
    sn, cos_min = _angle_gate(source_normals, max_angle_deg, source_points, dev, validate)
    return mod.associate_projective(source_points, _pose("T_target_source", T_target_source, dev),
                                    target_vertices.contiguous(), target_normals.contiguous(), sn,
                                    camera, float(max_distance), cos_min, b.device)


def associate_nearest(source_points: torch.Tensor, T_target_source, grid: PointGrid, *,  # [N, 3], [4, 4]
                      max_distance: float, validate: bool = True) -> torch.Tensor:
    """Nearest grid point within `max_distance` (metres, inclusive) of each T p -> int32 [N] index or -1."""
    b, mod = _be()
    dev = b.torch_device
    source_points = _points("source_points", source_points, dev, validate)
    if not max_distance > 0:
        raise InputError(f"argument 'max_distance': expected > 0, got {max_distance}")
    return mod.associate_nearest(grid._impl, grid.points, source_points, _pose("T_target_source", T_target_source, dev),
                                 float(max_distance), b.device)


def _photo(photometric: PhotometricTerm | None, N: int, dev, validate: bool):
    if photometric is None:
        return None
    cam = photometric.camera
    _check("photometric.source_intensity", photometric.source_intensity, (N,), device=dev, validate=validate)
    _check("photometric.target_intensity", photometric.target_intensity, (cam.height, cam.width), device=dev,
           validate=validate)
    _check("photometric.target_gradient", photometric.target_gradient, (cam.height, cam.width, 2), device=dev,
           validate=validate)
    return (photometric.source_intensity.contiguous(), photometric.target_intensity.contiguous(),
            photometric.target_gradient.contiguous(), cam, float(photometric.weight))


def _robust(robust: str, robust_scale: float) -> int:
    if robust not in ROBUST_KINDS:
        raise InputError(f"argument 'robust': expected one of {sorted(ROBUST_KINDS)}, got {robust!r}")
    if robust != "none" and not robust_scale > 0:
        raise InputError(f"argument 'robust_scale': expected > 0 for robust={robust!r}, got {robust_scale}")
    return ROBUST_KINDS[robust]


def reduce_point_to_plane(source_points: torch.Tensor, T_target_source,  # [N, 3], [4, 4]
                          target_points: torch.Tensor, target_normals: torch.Tensor,  # [M, 3] (or [H, W, 3]) each
                          idx: torch.Tensor, *, robust: str = "none", robust_scale: float = 0.0,  # [N] int32
                          photometric: PhotometricTerm | None = None, validate: bool = True) -> NormalEquations:
    """One pass over the associated points: JᵀWJ, JᵀWr, cost, squared distances and counts.

    robust: "none", "huber" or "tukey" with scale `robust_scale` (metres, > 0 unless "none"). The photometric
    term needs `target_points` to be the vertex map of `photometric.camera`. validate=False skips the O(N)
    NaN scans (shapes, dtypes and devices are always checked) for callers that validated their inputs once.
    """
    b, mod = _be()
    dev = b.torch_device
    source_points = _points("source_points", source_points, dev, validate)
    N = source_points.shape[0]
    tp = _points("target_points", target_points.reshape(-1, 3), dev, validate)
    tn = _check("target_normals", target_normals.reshape(-1, 3), (tp.shape[0], 3), device=dev, validate=validate)
    _check("idx", idx, (N,), dtypes=(torch.int32,), device=dev)
    kind = _robust(robust, robust_scale)
    sums = mod.reduce_point_to_plane(source_points, _pose("T_target_source", T_target_source, dev), tp,
                                     tn.contiguous(), idx.contiguous(), kind, float(robust_scale),
                                     _photo(photometric, N, dev, validate), b.device)
    return NormalEquations.from_sums(sums)


def projective_normal_equations(source_points: torch.Tensor, T_target_source,  # [N, 3], [4, 4]
                                target_vertices: torch.Tensor, target_normals: torch.Tensor,  # [H, W, 3] each
                                camera: PinholeCamera, *, max_distance: float,
                                source_normals: torch.Tensor | None = None, max_angle_deg: float | None = None,
                                robust: str = "none", robust_scale: float = 0.0,
                                photometric: PhotometricTerm | None = None, validate: bool = True) -> NormalEquations:
    """`associate_projective` and `reduce_point_to_plane` fused into one pass (no index array is written):
    the per-iteration step of projective ICP. Same gates, same sums; the photometric camera must be `camera`."""
    b, mod = _be()
    dev = b.torch_device
    source_points = _points("source_points", source_points, dev, validate)
    N = source_points.shape[0]
    H, W = camera.height, camera.width
    _check("target_vertices", target_vertices, (H, W, 3), device=dev, validate=validate)
    _check("target_normals", target_normals, (H, W, 3), device=dev, validate=validate)
    if photometric is not None and photometric.camera != camera:
        raise InputError("argument 'photometric': its camera must be the target camera of the projective association")
    sn, cos_min = _angle_gate(source_normals, max_angle_deg, source_points, dev, validate)
    kind = _robust(robust, robust_scale)
    sums = mod.reduce_point_to_plane(source_points, _pose("T_target_source", T_target_source, dev),
                                     target_vertices.reshape(-1, 3).contiguous(), target_normals.reshape(-1, 3).contiguous(),
                                     _dummy_idx(dev), kind, float(robust_scale), _photo(photometric, N, dev, validate),
                                     b.device, proj=(sn, camera, H, W, float(max_distance), cos_min))
    return NormalEquations.from_sums(sums)


def _angle_gate(source_normals, max_angle_deg, source_points, dev, validate) -> tuple[torch.Tensor, float]:
    if source_normals is None or max_angle_deg is None:
        return source_points, -2.0  # the kernels skip the gate when cos_min < -1
    _check("source_normals", source_normals, (source_points.shape[0], 3), device=dev, validate=validate)
    return source_normals.contiguous(), math.cos(math.radians(float(max_angle_deg)))


_DUMMY_IDX: dict = {}


def _dummy_idx(dev) -> torch.Tensor:
    key = str(dev)
    if key not in _DUMMY_IDX:
        _DUMMY_IDX[key] = torch.zeros(1, dtype=torch.int32, device=dev)
    return _DUMMY_IDX[key]


def n_blocks(n: int, device: str) -> tuple[int, int, int, int]:
    """Partition of n items into reduction blocks -> (blocks, start_stride, item_stride, items_per_block).

    CPU: a few contiguous chunks per core (cache-friendly, Taichi spreads blocks over cores). CUDA: many threads
    walking the array with a grid stride (coalesced). Item i of block b is b * start_stride + j * item_stride.
    """
    if device != "cpu":  # cuda, vulkan
        blocks = max(1, min(16384, n))
        return blocks, 1, blocks, (n + blocks - 1) // blocks
    blocks = max(1, min(64, n))
    chunk = (n + blocks - 1) // blocks
    return blocks, chunk, 1, chunk


_DUMMY_TERMS: dict = {}


@dataclass
class ReduceTerms:
    """The scalar and array arguments both backends' point-to-plane reduction kernels take, unpacked from
    `photo` = (source intensity, target intensity, target gradient [H, W, 2], camera, lambda) and `proj` =
    (source normals, camera, H, W, max_d, cos_min); placeholders (and has_photo / projective = 0) where absent."""

    s_int: torch.Tensor
    t_int: torch.Tensor
    gu: torch.Tensor
    gv: torch.Tensor
    lam: float
    has_photo: int
    projective: int
    sn: torch.Tensor
    th: int
    tw: int
    max_d: float
    cos_min: float
    fx: float
    fy: float
    cx: float
    cy: float


def reduce_terms(src: torch.Tensor, photo, proj) -> ReduceTerms:
    """See ReduceTerms; the placeholders are cached per device (kernels take no 0-sized arrays)."""
    key = str(src.device)
    if key not in _DUMMY_TERMS:
        _DUMMY_TERMS[key] = (torch.zeros(1, dtype=torch.float32, device=src.device),
                             torch.zeros(2, 2, dtype=torch.float32, device=src.device))
    s1, i2 = _DUMMY_TERMS[key]
    s_int, t_int, gu, gv, lam, has = s1, i2, i2, i2, 0.0, 0
    cam = None
    if photo is not None:
        s_int, t_int, grad, cam, lam = photo
        gu, gv, has = grad[..., 0].contiguous(), grad[..., 1].contiguous(), 1
    projective, sn, th, tw, max_d, cos_min = 0, src, 0, 0, 0.0, -2.0
    if proj is not None:
        sn, cam, th, tw, max_d, cos_min = proj
        projective = 1
    fx, fy, cx, cy = (cam.fx, cam.fy, cam.cx, cam.cy) if cam is not None else (1.0, 1.0, 0.0, 0.0)
    return ReduceTerms(s_int, t_int, gu, gv, lam, has, projective, sn, th, tw, max_d, cos_min, fx, fy, cx, cy)
