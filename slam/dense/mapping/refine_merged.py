"""Server-side global map refinement (GRAND-SLAM Fig. 2: the server "refines the global map").

After the final pose-graph optimisation the submaps of a component sit in one frame, but each submap was only
ever optimised for its own keyframes. Where neighbouring submaps overlap (they always do: every new submap starts
empty and seeds the whole view again) a view renders the Gaussians of two or three submaps blended together, none
of them fitted to that blend — measured on the default demo data this costs ~6 dB against each submap rendered
alone. Refinement optimises the *merged* map of a component over all its keyframes at their optimised poses with
the mapping loss (eq. 3), so the overlapping Gaussians are fitted jointly.

Each step renders one keyframe (a fresh random order every pass over the keyframes, so every keyframe is visited
equally) and back-propagates only into the Gaussians whose centre projects into that keyframe's view (with a
margin): the rasteriser's cost grows with the number of Gaussians it is handed, and most of a room-scale map is
outside any one view.

With `cfg.refine_poses` each keyframe's pose is refined with the map (a photometric bundle adjustment): every
step also moves the step's keyframe by a left twist, viewmat = exp(xi) @ viewmat0, through the rasteriser's pose
gradient, with Adam per keyframe. The first view (or `fixed_views`: a team's first keyframe of each agent) holds
the gauge (it is not moved). The map fitted over
keyframes whose poses are a few millimetres apart blurs every texture edge by that much; the refined poses are
returned (`RefineStats.viewmats`) so the caller renders and reports the trajectory at the poses the map was
fitted to.

    from swarmsplat.slam.dense.mapping.refine_merged import RefineView, refine_map
    refined, keep, stats = refine_map(params, views, cfg.map_refine, cfg.mapping)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera

from swarmsplat.slam.config import ExposureConfig, MappingConfig, MapRefineConfig
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from .mapper import ExposureSteps, make_optimizer, mapping_loss
from swarmsplat.slam.dense.param_ops import activate
from swarmsplat.slam.io.progress import bar
from swarmsplat.slam.dense.render import NEAR, render
from .selective_adam import SelectiveAdam


class RefineView:
    """One keyframe as refinement sees it: the map-to-camera matrix and its images.

    The images are tensors given as they are, or (`frame`: an RGBD or a packed keyframe, slam.dense.packed)
    made from the frame when they are read, through `cache` (a ViewCache shared by the views): a refinement over a
    long mission's keyframes then holds them as stored (PNG for a finished submap's keyframes) plus the decoded
    ones the cache keeps, instead of every view as float tensors at once (1.2 MB each at 320x240)."""

    __slots__ = ("viewmat", "camera", "_color", "_depth", "frame", "cache", "exposure", "exposure_prior",
                 "exposure_outlier")

    def __init__(self, viewmat: torch.Tensor, color: torch.Tensor | None, depth: torch.Tensor | None,
                 camera: PinholeCamera, *, frame=None, cache: "ViewCache | None" = None,
                 exposure: np.ndarray | None = None, exposure_prior: np.ndarray | None = None,
                 exposure_outlier: bool = False):
        self.viewmat = viewmat  # [4, 4] map frame -> camera (OpenCV axes)
        self.camera = camera
        self._color, self._depth, self.frame, self.cache = color, depth, frame, cache
        # the keyframe's exposure (slam.dense.mapping.exposure; None: no photometric model), its anchor, outlier
        self.exposure, self.exposure_prior, self.exposure_outlier = exposure, exposure_prior, exposure_outlier

    def at(self, viewmat: torch.Tensor | None = None, exposure: np.ndarray | None = None) -> "RefineView":
        """The same keyframe and images seen from `viewmat` (a refined pose) and/or with `exposure` (refined);
        None keeps the view's."""
        return RefineView(self.viewmat if viewmat is None else viewmat, self._color, self._depth, self.camera,
                          frame=self.frame, cache=self.cache,
                          exposure=self.exposure if exposure is None else exposure,
                          exposure_prior=self.exposure_prior, exposure_outlier=self.exposure_outlier)

    def _images(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self.cache is None:
            return decoded(self.frame)
        return self.cache.get(self.frame)

    def read(self, *, cached: bool = True) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(colour, depth); `cached=False` decodes a stored view without putting it in the cache (a pass that reads
        each view once, such as the overlap cull, would only push out the views the refinement reuses)."""
        if self._color is None and self.frame is not None:
            return self._images() if cached else decoded(self.frame)
        return self._color, self._depth

    @property
    def color(self) -> torch.Tensor | None:  # [H, W, 3] float in [0, 1]
        return self._images()[0] if self._color is None and self.frame is not None else self._color

    @property
    def depth(self) -> torch.Tensor | None:  # [H, W] metres, 0 = invalid
        return self._images()[1] if self._depth is None and self.frame is not None else self._depth


class ViewCache:
    """Decoded keyframe images (colour and depth tensors) by frame, least recently used dropped first once they
    pass `max_bytes`. `decoded` counts the decodes (hits are the other reads)."""

    def __init__(self, max_bytes: float):
        from collections import OrderedDict

        self.max_bytes = float(max_bytes)
        self.items: OrderedDict = OrderedDict()  # id(frame) -> (frame, color, depth)
        self.bytes = 0
        self.decoded = 0

    def get(self, frame) -> tuple[torch.Tensor, torch.Tensor]:
        hit = self.items.get(id(frame))
        if hit is not None and hit[0] is frame:
            self.items.move_to_end(id(frame))
            return hit[1], hit[2]
        color, depth = decoded(frame)
        self.decoded += 1
        size = color.numel() * color.element_size() + depth.numel() * depth.element_size()
        if size <= self.max_bytes:
            self.items[id(frame)] = (frame, color, depth)
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, (_, c, d) = self.items.popitem(last=False)
                self.bytes -= c.numel() * c.element_size() + d.numel() * d.element_size()
        return color, depth


def decoded(frame) -> tuple[torch.Tensor, torch.Tensor]:
    """(colour [H, W, 3], depth [H, W]) tensors of an RGBD or a packed frame, a packed one decoded (and read from
    its store) once for both."""
    f = frame.unpacked() if hasattr(frame, "unpacked") else frame
    return f.color_tensor(), f.depth_tensor()


@dataclass
class RefineStats:
    iterations: int
    views: int
    gaussians: int
    loss_first: float  # mean loss of the first pass over the views
    loss_last: float  # mean loss of the last pass
    seconds: float
    viewmats: list[torch.Tensor] | None = None  # [4, 4] per view after pose refinement (None: poses not refined)
    pose_moves: np.ndarray | None = None  # [views, 2] rotation (rad) and translation (m) each view was moved by
    exposures: list[np.ndarray | None] | None = None  # [6] per view after refinement (slam.dense.mapping.exposure)


class _PoseSteps:
    """Per-view left twists xi_j [omega, v] with viewmat_j = exp(xi_j) @ viewmat0_j, each stepped by its own Adam
    (a view's pose only has a gradient at its own steps). Views in `fixed` keep their pose."""

    def __init__(self, views: list[RefineView], lr_rotation: float, lr_translation: float, fixed: set[int]):
        self.vm0 = [v.viewmat.detach().to(torch.float64) for v in views]
        self.xi = torch.zeros(len(views), 6, dtype=torch.float64)
        self.m, self.v = torch.zeros_like(self.xi), torch.zeros_like(self.xi)
        self.t = [0] * len(views)
        self.lr = torch.tensor([lr_rotation] * 3 + [lr_translation] * 3, dtype=torch.float64)
        self.fixed = fixed

    def viewmat(self, j: int, view: RefineView) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(viewmat for the step's render, the twist leaf whose .grad the render's backward fills, or None)."""
        if j in self.fixed:
            return view.viewmat, None
        leaf = self.xi[j].clone().requires_grad_(True)
        return (se3.exp_torch(leaf) @ self.vm0[j]).to(view.viewmat.dtype), leaf

    def step(self, j: int, leaf: torch.Tensor | None) -> None:
        if leaf is None or leaf.grad is None:
            return
        g = leaf.grad.detach()
        b1, b2 = 0.9, 0.999
        self.t[j] += 1
        self.m[j] = b1 * self.m[j] + (1 - b1) * g
        self.v[j] = b2 * self.v[j] + (1 - b2) * g * g
        m_hat = self.m[j] / (1 - b1 ** self.t[j])
        v_hat = self.v[j] / (1 - b2 ** self.t[j])
        self.xi[j] -= self.lr * m_hat / (v_hat.sqrt() + 1e-12)

    def result(self, dtype) -> tuple[list[torch.Tensor], np.ndarray]:
        mats = [(se3.exp_torch(x) @ m).to(dtype) for x, m in zip(self.xi, self.vm0)]
        moves = np.stack([self.xi[:, :3].norm(dim=1).numpy(), np.zeros(len(self.xi))], axis=1)
        for j, (T, T0) in enumerate(zip(mats, self.vm0)):  # translation of the camera centre, metres
            c = -T[:3, :3].double().T @ T[:3, 3].double()
            c0 = -T0[:3, :3].T @ T0[:3, 3]
            moves[j, 1] = float((c - c0).norm())
        return mats, moves


def refines_poses(cfg: MapRefineConfig, keyframes) -> bool:
    """Whether a refinement over `keyframes` (Keyframes or RefineViews) refines their poses: `cfg.refine_poses`
    true, or "auto" and the camera's exposure model on for one of them (a keyframe carries an exposure once its
    agent's model is on, slam.dense.agent)."""
    if cfg.refine_poses == "auto":
        return any(getattr(kf, "exposure", None) is not None for kf in keyframes)
    return bool(cfg.refine_poses)


def iteration_budget(cfg: MapRefineConfig, n_views: int) -> int:
    """Steps for a component with `n_views` keyframes: iterations_per_keyframe each, capped at max_iterations."""
    return int(min(cfg.max_iterations, cfg.iterations_per_keyframe * n_views))


class Visibility:
    """Which Gaussians (centres `means` [N, 3], map frame, held as given) a view sees, for many views: the centres
    kept as a [3, N] copy, so each view costs one small matrix product over them and five comparisons (measured on a
    0.85 M-Gaussian map: 8 against 20 ms per view for projecting every centre, most of a refinement step's time
    outside the rasteriser)."""

    def __init__(self, means: torch.Tensor):
        self.means_t = means.detach().T.contiguous()

    def indices(self, view: RefineView, margin: float) -> torch.Tensor:
        """Indices of the Gaussians whose centre is in front of the camera (z > NEAR) and projects inside the image
        grown by `margin` x its size on every side; the margin covers Gaussians centred outside the image whose
        footprint reaches into it. The image bounds as half-spaces in the camera frame (u > -m_u is
        fx x + (cx + m_u) z > 0 for z > 0), mapped to the map frame by the view's pose: one [5, 3] product."""
        cam = view.camera
        R = view.viewmat[:3, :3].to(torch.float64)
        t = view.viewmat[:3, 3].to(torch.float64)
        mu, mv = margin * cam.width, margin * cam.height
        planes = torch.tensor([[cam.fx, 0.0, cam.cx + mu], [-cam.fx, 0.0, cam.width + mu - cam.cx],
                               [0.0, cam.fy, cam.cy + mv], [0.0, -cam.fy, cam.height + mv - cam.cy],
                               [0.0, 0.0, 1.0]], dtype=torch.float64)
        offset = torch.tensor([0.0, 0.0, 0.0, 0.0, -NEAR], dtype=torch.float64)
        dtype = self.means_t.dtype
        with torch.no_grad():
            vals = torch.addmm((planes @ t + offset).to(dtype)[:, None], (planes @ R).to(dtype), self.means_t)
            inside = vals[0] > 0
            for k in range(1, len(vals)):
                inside &= vals[k] > 0
        return torch.nonzero(inside).squeeze(1)


def visible_indices(means: torch.Tensor, view: RefineView, margin: float) -> torch.Tensor:
    """Indices of the Gaussians whose centre (means [N, 3], map frame) is in front of the camera and projects
    inside the image grown by `margin` x its size on every side (Visibility, for one view)."""
    return Visibility(means).indices(view, margin)


def contributions(params: GaussianParams, views: list[RefineView]) -> torch.Tensor:
    """[N] the largest total blending weight (sum over pixels of alpha x transmittance, in pixels) each Gaussian
    has in any of `views`: the gradient of the summed rendered colour with respect to its colour."""
    p = params.detached()
    p.colors = p.colors.clamp(0.0, 1.0).requires_grad_(True)
    w = torch.zeros(len(p), dtype=p.means.dtype)
    for v in views:
        p.colors.grad = None
        render(p, v.viewmat, v.camera).color.sum().backward()
        w = torch.maximum(w, p.colors.grad.detach().sum(dim=1) / 3.0)
    return w


def _scatter_grads(tensors: list[torch.Tensor], idx: torch.Tensor, grads: list[torch.Tensor | None]) -> None:
    """tensors[i].grad = zeros with grads[i] at rows idx (unique): what backward through tensors[i][idx] gives
    (None where grads[i] is None)."""
    for t, g in zip(tensors, grads):
        if g is None:  # no gradient reached these rows: Adam skips the tensor, as after zero_grad(set_to_none)
            t.grad = None
            continue
        if t.grad is None:
            t.grad = torch.zeros_like(t)
        else:
            t.grad.zero_()
        t.grad.index_copy_(0, idx, g)


def lr_factor(final: float, step: int, steps: int) -> float:
    """The learning-rate multiplier of step `step` (0-based) of `steps`: geometric from 1 at the first step to
    `final` at the last (MapRefineConfig.lr_final_scale)."""
    return float(final) ** (step / max(1, steps - 1))


def refine_map(params: GaussianParams, views: list[RefineView], cfg: MapRefineConfig, mapping: MappingConfig, *,
               iterations: int | None = None, fixed_views: set[int] | None = None,
               context: GaussianParams | None = None, exposure: ExposureConfig | None = None,
               exposure_gauge: set[int] | None = None) -> tuple[GaussianParams, torch.Tensor, RefineStats]:
    """Optimise every Gaussian of `params` (one component's merged map, in its frame) over `views` with Adam: the
    mapping loss (eq. 3, masks from `mapping`, λ_c and the isotropic penalty from `cfg`), the mapping learning
    rates x `cfg.lr_scale`, decaying geometrically to `cfg.lr_final_scale` of that at the last step (`lr_factor`).
    `cfg.optimizer`: "selective" updates only the Gaussians of the step's view (slam.dense.mapping.selective_adam), "adam" is
    torch's Adam over the whole map every step.

    First, Gaussians that contribute less than `cfg.min_contribution` pixels to every view are dropped: where
    submaps overlap, the surface of one hides the same surface of another, and those hidden copies only cost
    time (measured: half of one agent's merged map, with the same PSNR after refinement).

    With `cfg.refine_poses` the views' poses are refined too, all but `fixed_views` (default: the first view,
    which holds the gauge): `stats.viewmats` has them, `stats.pose_moves` how far each moved.

    With `exposure` (slam.dense.mapping.exposure) every view with an exposure has it optimised too, all but
    `exposure_gauge` (default: `fixed_views`; a team's first keyframe of one agent only, since all agents' colours
    meet in one map), regularised toward its anchor with `cfg.exposure_regulariser` and stepped with
    `cfg.exposure_lr` (the refinement's own, in place of `exposure`'s); `stats.exposures` has them. An outlier
    view's colour takes no part in the loss.

    `context`: Gaussians rendered with `params` at every step (those in the step's view) but not optimised: the
    rest of the map when `params` is one region of it (slam.dense.mapping.refine_regions).

    Returns (kept Gaussians, refined, in their original order; keep [N] bool over the input; statistics), so the
    caller can hand each submap its own surviving Gaussians back. `iterations` overrides the budget.
    """
    t0 = time.perf_counter()
    n_it = iteration_budget(cfg, len(views)) if iterations is None else int(iterations)
    keep = torch.ones(len(params), dtype=torch.bool)
    if n_it <= 0 or not views or len(params) == 0:
        return params.detached(), keep, RefineStats(0, len(views), len(params), float("nan"), float("nan"), 0.0)
    if cfg.min_contribution > 0:
        keep = contributions(params, views) >= cfg.min_contribution
    gen = torch.Generator().manual_seed(cfg.seed)
    p = params.select(keep).requires_grad_(cfg.optimizer == "adam")
    lr = cfg.lr_scale
    lrs = [mapping.lr_means * lr, mapping.lr_log_scales * lr, mapping.lr_quats * lr, mapping.lr_opacities * lr,
           mapping.lr_colors * lr]
    tensors = [p.means, p.log_scales, p.quats, p.logit_opacities, p.colors]
    if cfg.optimizer == "selective":
        sel = SelectiveAdam(tensors, lrs)
    else:  # mapping's Adam, fused: a step over a 211k-Gaussian map takes 2.7 ms instead of 9.0 ms (for-loop Adam)
        opt = make_optimizer(p, mapping, lr)
    # Visibility from the starting means: refinement moves a Gaussian by millimetres, far less than the margin.
    # Found again at each step from one copy of them rather than kept per view: in a revisited place every view
    # sees a large share of the map, and views x visible indices grew with the square of the mission.
    seen = Visibility(p.means)
    ctx = None if context is None or len(context) == 0 else context.map(torch.Tensor.detach)
    ctx_seen = None if ctx is None else Visibility(ctx.means)
    poses = (_PoseSteps(views, cfg.lr_pose_rotation, cfg.lr_pose_translation,
                        fixed={0} if fixed_views is None else set(fixed_views))
             if refines_poses(cfg, views) and len(views) > 1 else None)
    gauge = {0} if fixed_views is None else set(fixed_views)
    ex_gauge = gauge if exposure_gauge is None else set(exposure_gauge)
    if exposure is not None:  # the refinement's own prior and step (MapRefineConfig.exposure_*)
        exposure = exposure.model_copy(update={"regulariser": cfg.exposure_regulariser, "lr": cfg.exposure_lr})
    ex = ExposureSteps([v.exposure for v in views], [v.exposure_prior for v in views],
                       [j in ex_gauge for j in range(len(views))], exposure)
    order: list[int] = []
    losses: list[float] = []
    b = bar(n_it, "[refine] steps", unit="step", enabled=None)  # shown inside slam.io.progress.reporting(True)
    base = list(sel.lrs) if cfg.optimizer == "selective" else [g["lr"] for g in opt.param_groups]
    for it in range(n_it):
        b.update(1, f"loss {losses[-1]:.4f}" if losses else None)
        if cfg.lr_final_scale != 1.0:
            f = lr_factor(cfg.lr_final_scale, it, n_it)
            if cfg.optimizer == "selective":
                sel.lrs = [lr * f for lr in base]
            else:
                for g, lr in zip(opt.param_groups, base):
                    g["lr"] = lr * f
        if not order:
            order = torch.randperm(len(views), generator=gen).tolist()
        j = order.pop()
        idx = seen.indices(views[j], cfg.view_margin)
        if len(idx) == 0:
            continue
        v = views[j]
        # The view's rows as leaves of their own (index_select); "adam" then scatters their gradients into the
        # map's zeroed ones, the gradient autograd's indexing gives, bit for bit, at half its cost (measured over
        # the demo's 211k-Gaussian map, 114k rows per view: 8 vs 15 ms per step).
        sub = GaussianParams(*(t.detach().index_select(0, idx).requires_grad_(True) for t in tensors))
        viewmat, leaf = poses.viewmat(j, v) if poses is not None else (v.viewmat, None)
        drawn = sub
        if ctx is not None:  # the frozen rest of the map in this view, drawn with the step's Gaussians
            cidx = ctx_seen.indices(v, cfg.view_margin)
            if len(cidx):
                drawn = GaussianParams(*(torch.cat([a, b.index_select(0, cidx)])
                                         for a, b in zip(sub.tensors(), ctx.tensors())))
        act = activate(drawn)
        out = render(drawn, viewmat, v.camera, activated=act)
        ex.zero_grad()
        lambda_color = 0.0 if v.exposure_outlier else cfg.lambda_color
        loss = mapping_loss(ex.color(j, out), v.color, v.depth, drawn, mapping, lambda_color,
                            cfg.isotropic_regulariser, act) + ex.penalty(j)
        loss.backward()
        ex.step()
        if poses is not None:
            poses.step(j, leaf)
        grads = [sub.means.grad, sub.log_scales.grad, sub.quats.grad, sub.logit_opacities.grad, sub.colors.grad]
        if cfg.optimizer == "selective":
            sel.step(idx, grads)
        else:
            _scatter_grads(tensors, idx, grads)
            opt.step()
        losses.append(float(loss.detach()))
    b.close()
    k = max(1, min(len(views), len(losses)))
    first = float(np.mean(losses[:k])) if losses else float("nan")
    last = float(np.mean(losses[-k:])) if losses else float("nan")
    mats, moves = poses.result(views[0].viewmat.dtype) if poses is not None else (None, None)
    exposures = [ex.result(j) for j in range(len(views))]
    return p.detached(), keep, RefineStats(len(losses), len(views), len(params), first, last,
                                           time.perf_counter() - t0, mats, moves, exposures)
