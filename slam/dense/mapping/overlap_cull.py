"""One copy of each surface where submaps overlap, before the merged map is refined (slam.dense.mapping.refine).

Every new submap starts empty and seeds its whole first view again, and agents revisit each other's rooms, so
a merged map holds two or three copies of most surfaces, each fitted to its own submap's keyframes only. The
refinement's first cull (MapRefineConfig.min_contribution) drops the copies that are fully hidden behind another;
the copies that interleave with another at the same depth (both on the surface, ±noise) stay and blend there.

Here every Gaussian is given to one owner submap: among the keyframes that *observe its centre on their depth
surface* (the centre projects into the keyframe's image, in front of the camera, within a depth tolerance of the
keyframe's depth at that pixel), the one that sees it from closest (finest pixel footprint) names the owner. A
Gaussian survives in its owner only; a Gaussian that no keyframe observes on its surface (a floater, a
depth-less region) is kept. The owners partition each surface into patches, each rendered by the submap that saw
it in most detail, and the refinement then fits the seams. Gaussians that mapping seeded in large regions without
depth (slam.dense.mapping.mapper.fallback_depth: windows, sky) have no measured surface to be observed on; those that project
into such a region of a view are owned by the nearest such view (`OwnerView.no_depth`).

Measured on Redwood 211 (one agent, 5 submaps, 43 keyframes, 320x240): 256k -> 108k Gaussians; the merged map
before refinement 23.33 -> 23.62 dB; after the same 344 refinement steps 27.26 dB against 27.09, in 57 s against
100 s (README "Merged-map overlap cull").

    from swarmsplat.slam.dense.mapping.overlap_cull import OwnerView, owner_keep
    keep = owner_keep(means_world, part_of_gaussian, [OwnerView(part, viewmat, depth, camera), ...], cfg)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from swarmsplat.kernels.camera import PinholeCamera

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.dense.render import NEAR


@dataclass
class OwnerView:
    """One keyframe as the cull sees it: the part (submap) it belongs to, where it looks from, what it measured."""

    part: int  # index of the keyframe's submap in the caller's list of parts
    viewmat: torch.Tensor  # [4, 4] map frame -> camera (OpenCV axes)
    depth: torch.Tensor  # [H, W] metres, 0 = invalid
    camera: PinholeCamera
    no_depth: torch.Tensor | None = None  # [H, W] bool: the large regions without depth mapping seeded


def owner_keep(means: torch.Tensor, part: torch.Tensor, views: list[OwnerView], *, tol_abs: float = 0.03,
               tol_rel: float = 0.02) -> torch.Tensor:
    """keep [N] bool: Gaussian i (centre means[i] in the map frame, of part part[i]) survives when the nearest
    keyframe observing its centre on the keyframe's depth surface (|z - D(u, v)| < max(tol_abs, tol_rel D))
    belongs to part[i], or when no keyframe observes it. Ties go to the view listed first. A Gaussian no keyframe
    observes on a surface but that projects into a view's `no_depth` region (mapping's seeds without depth, which
    have no measured depth to compare with) is owned by the nearest such view."""
    means = torch.as_tensor(means)
    part = torch.as_tensor(part, dtype=torch.long)
    if means.ndim != 2 or means.shape[1] != 3 or part.shape != (len(means),):
        raise InputError(f"owner_keep: expected means [N, 3] and part [N], got {list(means.shape)} and "
                         f"{list(part.shape)}")
    if tol_abs < 0 or tol_rel < 0:
        raise InputError(f"owner_keep: depth tolerances must be >= 0, got tol_abs={tol_abs}, tol_rel={tol_rel}")
    n = len(means)
    best = torch.full((n,), float("inf"), dtype=torch.float32)
    owner = torch.full((n,), -1, dtype=torch.long)
    best_nd = torch.full((n,), float("inf"), dtype=torch.float32)
    owner_nd = torch.full((n,), -1, dtype=torch.long)
    m = means.detach().to(torch.float32)
    groups = _groups(m, part)
    for v in views:
        cam = v.camera
        depth = torch.as_tensor(v.depth, dtype=torch.float32)
        if depth.shape != (cam.height, cam.width):
            raise InputError(f"owner_keep: a view's depth is {list(depth.shape)}, its camera is "
                             f"{cam.width}x{cam.height}")
        R, t = v.viewmat[:3, :3].to(torch.float32), v.viewmat[:3, 3].to(torch.float32)
        no_depth = None if v.no_depth is None else torch.as_tensor(v.no_depth, dtype=torch.bool)
        seen = [g for g, corners in groups if _box_in_view(corners, R, t, cam)]
        for chunk in _chunks(seen):
            pc = m[chunk] @ R.T + t
            z = pc[:, 2]
            zs = z.clamp_min(NEAR)
            u = torch.round(cam.fx * pc[:, 0] / zs + cam.cx)  # nearest pixel (OpenCV: centres at integers)
            w = torch.round(cam.fy * pc[:, 1] / zs + cam.cy)
            inside = (z > NEAR) & (u >= 0) & (w >= 0) & (u < cam.width) & (w < cam.height)
            sel = torch.nonzero(inside).squeeze(1)
            idx = chunk[sel]
            ui, wi = u[sel].long(), w[sel].long()
            d = depth[wi, ui]
            zi = z[sel]
            on_surface = (d > 0) & ((zi - d).abs() < torch.clamp(tol_rel * d, min=tol_abs)) & (zi < best[idx])
            hit = idx[on_surface]
            best[hit] = zi[on_surface]
            owner[hit] = int(v.part)
            if no_depth is not None:
                nd = no_depth[wi, ui] & (zi < best_nd[idx])
                hit = idx[nd]
                best_nd[hit] = zi[nd]
                owner_nd[hit] = int(v.part)
    owner = torch.where(owner < 0, owner_nd, owner)
    return (owner < 0) | (owner == part)


CHUNK = 1 << 18  # Gaussians projected at once: the per-view temporaries stay a few MB however large the map


_CORNER = torch.tensor([[(k >> a) & 1 for a in range(3)] for k in range(8)], dtype=torch.bool)  # [8, 3]: True where a corner takes the max


def _groups(means: torch.Tensor, part: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(indices, the 8 corners [8, 3] of their bounding box)] of each part's Gaussians: a view then projects only
    the parts whose box it can see (a long mission's map is many rooms, a view sees one)."""
    out = []
    if len(part) == 0:
        return out
    order = torch.argsort(part, stable=True)
    _, counts = torch.unique_consecutive(part[order], return_counts=True)
    for idx in torch.split(order, counts.tolist()):
        pts = means[idx]
        out.append((idx, torch.where(_CORNER, pts.max(dim=0).values, pts.min(dim=0).values)))
    return out


def _box_in_view(corners: torch.Tensor, R: torch.Tensor, t: torch.Tensor, cam: PinholeCamera) -> bool:
    """False only when no point of the box with these corners [8, 3] (map frame) can project into the image in
    front of the camera: every corner behind it, or every corner in front and the corners' projections' bounding
    box (which holds the box's projection) off the image."""
    pc = corners @ R.T + t
    z = pc[:, 2]
    if bool((z <= NEAR).all()):
        return False
    if bool((z <= NEAR).any()):
        return True  # the box reaches behind the camera: its projection is unbounded
    u = cam.fx * pc[:, 0] / z + cam.cx
    v = cam.fy * pc[:, 1] / z + cam.cy
    m = 1.0  # pixels beyond the rounding's half: float32 round-off never drops a Gaussian the full test keeps
    return bool(u.max() >= -0.5 - m and u.min() < cam.width - 0.5 + m and v.max() >= -0.5 - m
                and v.min() < cam.height - 0.5 + m)


def _chunks(groups: list[torch.Tensor]):
    """The indices of `groups`, at most CHUNK at a time (whole groups joined while they fit)."""
    batch, size = [], 0
    for g in groups:
        for a in range(0, len(g), CHUNK):
            piece = g[a:a + CHUNK]
            if size + len(piece) > CHUNK and batch:
                yield torch.cat(batch)
                batch, size = [], 0
            batch.append(piece)
            size += len(piece)
    if batch:
        yield torch.cat(batch)
