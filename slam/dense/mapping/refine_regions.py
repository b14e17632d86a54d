"""The merged-map refinement region by region, so that what it optimises at once is bounded by a region, not by
the mission (MapRefineConfig.region_gaussians).

A map of more than `region_gaussians` Gaussians (after the overlap cull) is split in space into regions of at most
that many (`split_regions`: a balanced k-d split of the centres along their widest axis). The regions are refined
one after the other, each starting from what the regions before left, in `SWEEPS` passes:

- a region optimises its own Gaussians only, over the keyframes that see them (centre in the view, with the view
  margin, and not behind the view's measured depth: `unoccluded`): every keyframe that sees at least `GLIMPSE`
  (10 %) of the region or for which the region holds at least that share of what it sees, and each keyframe in the
  region holding most of what it sees (its home). So each Gaussian is fitted to the views that see it, as in the
  whole-map refinement, bar the views that only glimpse its region (a few of its Gaussians through a door, at the
  image's margin), which would cost a whole step for a few Gaussians;
- each step renders the region's Gaussians together with the rest of the map in that view, frozen (`context` of
  refine_map), so a view's loss is the loss of the whole map in it and the seams between regions are fitted;
- each of those keyframes is visited as often as in the whole-map refinement (iterations_per_keyframe, or the
  share max_iterations leaves per keyframe), so a Gaussian gets as many updates as there, spread over `SWEEPS`
  passes over the regions (a region fitted against its neighbours' old state is refitted once they have moved).
  A keyframe that sees several regions is visited in each: the refinement's time grows with how much the regions'
  views overlap (in a single room every view sees every region: time x regions), its memory does not.

Gradients, Adam's two moments and the step's copies (five times a Gaussian's 56 bytes) are a region's; the map's
parameters themselves (56 bytes per Gaussian after the overlap cull) stay in memory once, as the frozen context.

The hidden-copy cull (MapRefineConfig.min_contribution) keeps its meaning: each Gaussian's largest contribution
over every keyframe, computed a view at a time over the Gaussians in that view. With pose refinement each keyframe
is moved in one region only, its home (the region with most of the Gaussians it sees), and held in the others; the
caller's fixed views (default: the first) hold the gauge everywhere.

A map of at most `region_gaussians` Gaussians (or region_gaussians 0), before or after the hidden-copy cull, is one
region: `refine_map` itself, bit for bit. (Regions cost time where views overlap; a map that only passed the bound
with its hidden copies is refined whole: the HoloLens walk's 1.07 M Gaussians after the overlap cull are 0.85 M
after it, and refined whole give the regions' merged map in two thirds of the time, docs/decisions/0019.)

    from swarmsplat.slam.dense.mapping.refine_regions import refine_by_region
    refined, keep, stats, info = refine_by_region(params, views, cfg.map_refine, cfg.mapping)
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from swarmsplat.slam.config import ExposureConfig, MappingConfig, MapRefineConfig
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from .refine_merged import (RefineStats, RefineView, Visibility, contributions, iteration_budget, refine_map,
                            refines_poses, visible_indices)


SWEEPS = 3  # passes over the regions, each with a third of the steps and of the learning-rate decay: a region
# fitted against its neighbours' state before they moved is refitted after. A toy wall in twelve strips
# (tests/test_refine_regions.py), mean colour error: one pass 0.057, two 0.044, three 0.038; refined whole 0.038.
GLIMPSE = 0.1  # a view visits a region holding at least this share of what it sees, or seeing this share of it


def split_regions(points: np.ndarray | torch.Tensor, max_size: int) -> list[np.ndarray]:
    """Indices (ascending) of the points [N, 3] in each region: ceil(N / max_size) regions of at most `max_size`
    points, made by splitting along the widest axis, each side given points in proportion to the regions it is to
    hold. max_size <= 0 or N <= max_size: one region."""
    pts_all = np.asarray(points, dtype=np.float64)
    n = len(pts_all)
    if max_size <= 0 or n <= max_size:
        return [np.arange(n)]

    def split(idx: np.ndarray, m: int) -> list[np.ndarray]:
        if m <= 1:
            return [np.sort(idx)]
        pts = pts_all[idx]
        axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
        order = idx[np.argsort(pts[:, axis], kind="stable")]
        m1 = m // 2
        n1 = int(round(len(idx) * m1 / m))
        return split(order[:n1], m1) + split(order[n1:], m - m1)

    return split(np.arange(n), math.ceil(n / max_size))


def whole_map_keep(params: GaussianParams, views: list[RefineView], min_contribution: float, margin: float
                   ) -> torch.Tensor:
    """keep [N]: the hidden-copy cull (refine_map's `contributions(params, views) >= min_contribution`) a view at
    a time over the Gaussians whose centre that view sees, so no step holds the whole map's render state."""
    best = torch.zeros(len(params), dtype=params.means.dtype)
    seen = Visibility(params.means)
    for v in views:
        idx = seen.indices(v, margin)
        if len(idx):
            best[idx] = torch.maximum(best[idx], contributions(params.select(idx), [v]))
    return best >= min_contribution


def unoccluded(means: torch.Tensor, view: RefineView, cfg: MapRefineConfig) -> torch.Tensor:
    """Indices of the Gaussians (centres `means` [N, 3]) that `view` sees: centre in the view (with the view
    margin) and not behind the view's measured surface (depth at its pixel, the nearest inside the image, plus the
    overlap cull's tolerance; where the view has no depth, any). In a building a view's frustum crosses walls into
    the next rooms; the depth keeps what is behind them out of the view's share of each region."""
    idx = visible_indices(means, view, cfg.view_margin)
    if len(idx) == 0:
        return idx
    depth = view.read(cached=False)[1]
    if depth is None:
        return idx
    cam = view.camera
    R, t = view.viewmat[:3, :3].to(means.dtype), view.viewmat[:3, 3].to(means.dtype)
    with torch.no_grad():
        pc = means[idx] @ R.T + t
        z = pc[:, 2]
        u = (cam.fx * pc[:, 0] / z + cam.cx).round().clamp(0, cam.width - 1).long()
        w = (cam.fy * pc[:, 1] / z + cam.cy).round().clamp(0, cam.height - 1).long()
        d = depth.to(means.dtype)[w, u]
        tol = torch.clamp(cfg.overlap_depth_tolerance_rel * d, min=cfg.overlap_depth_tolerance)
        keep = (d <= 0) | (z <= d + tol)
    return idx[keep]


def refine_by_region(params: GaussianParams, views: list[RefineView], cfg: MapRefineConfig,
                     mapping: MappingConfig, *, fixed_views: set[int] | None = None,
                     exposure: ExposureConfig | None = None, exposure_gauge: set[int] | None = None
                     ) -> tuple[GaussianParams, torch.Tensor, RefineStats, dict]:
    """refine_map's result (kept Gaussians refined, in order; keep [N] over the input; statistics) with the work done
    region by region (module docstring), and {"regions": how many, "region_gaussians_max": the most Gaussians one
    optimised, "region_keyframes_max": the most keyframes one visited}."""
    cfg = cfg.model_copy(update={"refine_poses": refines_poses(cfg, views)})  # one decision for every region
    n_it = iteration_budget(cfg, len(views))
    if cfg.region_gaussians <= 0 or len(params) <= cfg.region_gaussians or n_it <= 0 or not views:
        refined, keep, st = refine_map(params, views, cfg, mapping, fixed_views=fixed_views, exposure=exposure,
                                       exposure_gauge=exposure_gauge)
        return refined, keep, st, {"regions": 1, "region_gaussians_max": int(keep.sum()),
                                   "region_keyframes_max": len(views)}
    t0 = time.perf_counter()
    keep = (whole_map_keep(params, views, cfg.min_contribution, cfg.view_margin) if cfg.min_contribution > 0
            else torch.ones(len(params), dtype=torch.bool))
    out = params.select(keep)  # the map, updated region after region
    if len(out) <= cfg.region_gaussians:  # within the bound once the hidden copies are gone: one region after all
        refined, _, st = refine_map(out, views, cfg.model_copy(update={"min_contribution": 0.0}), mapping,
                                    fixed_views=fixed_views, exposure=exposure, exposure_gauge=exposure_gauge)
        st.gaussians, st.seconds = len(params), time.perf_counter() - t0
        return refined, keep, st, {"regions": 1, "region_gaussians_max": len(out),
                                   "region_keyframes_max": len(views)}
    tensors = out.tensors()
    regions = split_regions(out.means.detach().numpy(), cfg.region_gaussians)
    # which regions each view sees (with how many of their Gaussians), and each view's home region
    seen = np.zeros((len(views), len(regions)), dtype=np.int64)
    region_of = torch.empty(len(out), dtype=torch.long)
    for k, r in enumerate(regions):
        region_of[torch.as_tensor(r)] = k
    for j, v in enumerate(views):
        idx = unoccluded(out.means.detach(), v, cfg)
        seen[j] = np.bincount(region_of[idx].numpy(), minlength=len(regions))
    home = seen.argmax(axis=1)
    # a view takes part in a region unless it only glimpses it: less than GLIMPSE of what the view sees and less
    # than GLIMPSE of the region (a few Gaussians through a door); always in its home region
    of_view = seen / np.maximum(seen.sum(axis=1, keepdims=True), 1)
    of_region = seen / np.maximum(np.array([len(r) for r in regions])[None, :], 1)
    takes_part = (of_view >= GLIMPSE) | (of_region >= GLIMPSE) | (np.arange(len(regions))[None, :] == home[:, None])
    takes_part &= seen > 0
    gauge = {0} if fixed_views is None else set(fixed_views)
    ex_gauge = gauge if exposure_gauge is None else set(exposure_gauge)
    per_view = n_it / len(views)  # visits of each keyframe in the whole-map refinement
    current = list(views)
    moved = cfg.refine_poses and len(views) > 1
    iters, firsts, lasts, most_views = 0, [], [], 0
    # the learning rate decays over the sweeps as over the whole-map refinement's steps: each sweep takes its part
    decay = cfg.lr_final_scale ** (1.0 / SWEEPS)
    for sweep in range(SWEEPS):
        swept = cfg.model_copy(update={"min_contribution": 0.0, "lr_scale": cfg.lr_scale * decay ** sweep,
                                       "lr_final_scale": decay})
        for k, r in enumerate(regions):
            vs = np.nonzero(takes_part[:, k])[0]
            most_views = max(most_views, len(vs))
            total = per_view * len(vs)  # the region's steps, shared among the sweeps to add up exactly
            steps = int(round(total * (sweep + 1) / SWEEPS)) - int(round(total * sweep / SWEEPS))
            if steps <= 0 or len(vs) == 0:
                continue
            rows = torch.as_tensor(r)
            others = torch.ones(len(out), dtype=torch.bool)
            others[rows] = False
            sub = GaussianParams(*(t.index_select(0, rows) for t in tensors))
            fixed = {i for i, j in enumerate(vs.tolist()) if j in gauge or home[j] != k}
            ex_fixed = {i for i, j in enumerate(vs.tolist()) if j in ex_gauge or home[j] != k}
            refined, _, st = refine_map(sub, [current[j] for j in vs],
                                        swept.model_copy(update={"seed": cfg.seed + sweep * len(regions) + k}),
                                        mapping, iterations=steps, fixed_views=fixed, context=out.select(others),
                                        exposure=exposure, exposure_gauge=ex_fixed)
            for t, new in zip(tensors, refined.tensors()):
                t.index_copy_(0, rows, new)
            iters += st.iterations
            if st.iterations and sweep == 0:
                firsts.append((st.loss_first, st.iterations))
            if st.iterations and sweep == SWEEPS - 1:
                lasts.append((st.loss_last, st.iterations))
            for i, j in enumerate(vs.tolist()):  # a view's pose and exposure move in its home region only
                if home[j] == k and (st.viewmats is not None or st.exposures is not None):
                    current[j] = current[j].at(None if st.viewmats is None else st.viewmats[i],
                                               None if st.exposures is None else st.exposures[i])

    def mean(pairs):
        return float(np.average([x for x, _ in pairs], weights=[w for _, w in pairs])) if pairs else float("nan")

    viewmats = moves = None
    if moved:
        viewmats = [v.viewmat for v in current]
        moves = np.zeros((len(views), 2))
        for j, (a, b) in enumerate(zip(views, current)):
            T0, T = a.viewmat.double(), b.viewmat.double()
            cos = ((T[:3, :3] @ T0[:3, :3].T).trace() - 1) / 2
            moves[j, 0] = float(torch.arccos(cos.clamp(-1.0, 1.0)))
            moves[j, 1] = float((-T[:3, :3].T @ T[:3, 3] + T0[:3, :3].T @ T0[:3, 3]).norm())
    stats = RefineStats(iters, len(views), len(params), mean(firsts), mean(lasts), time.perf_counter() - t0,
                        viewmats, moves, [v.exposure for v in current])
    return out, keep, stats, {"regions": len(regions), "region_gaussians_max": max(len(r) for r in regions),
                              "region_keyframes_max": most_views}
