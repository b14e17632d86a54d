"""Gaussian maps grouped in submaps, each in its own local frame (GRAND-SLAM §III-B, eqs. 1, 2, 15).

Parameters are stored in the optimiser's parametrisation, the 3DGS way, so torch's Adam works on them directly:
  means            [N, 3]  metres, submap-local frame
  log_scales       [N, 3]  log of the per-axis standard deviations (metres)
  quats            [N, 4]  wxyz, not necessarily normalised (the rasteriser normalises)
  logit_opacities  [N]     logit of the opacity in (0, 1)
  colors           [N, 3]  RGB in [0, 1] (clamped when rendered or saved)

A submap's local frame is the camera frame of its first keyframe (identity there); `T_world_local` places it in
the agent's world frame and is what pose-graph optimisation changes (eq. 14). Moving a submap never touches its
optimised parameters unless asked: `merged()` applies each submap's `T_world_local` on the fly (eq. 15).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError

_PARAM_NAMES = ("means", "log_scales", "quats", "logit_opacities", "colors")
_PARAM_TAIL = {"means": (3,), "log_scales": (3,), "quats": (4,), "logit_opacities": (), "colors": (3,)}


@dataclass
class GaussianParams:
    """A set of Gaussians in the optimiser's parametrisation (see module docstring for units)."""

    means: torch.Tensor  # [N, 3]
    log_scales: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] wxyz
    logit_opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N, 3]

    def __post_init__(self):
        n = self.means.shape[0] if self.means.dim() >= 1 else -1
        for name in _PARAM_NAMES:
            x = getattr(self, name)
            if not isinstance(x, torch.Tensor):
                raise InputError(f"GaussianParams.{name}: expected a torch.Tensor, got {type(x).__name__}")
            want = (n,) + _PARAM_TAIL[name]
            if tuple(x.shape) != want:
                raise InputError(f"GaussianParams.{name}: expected shape {list(want)}, got {list(x.shape)}")

    # ---- construction -------------------------------------------------------------------------------------

    @classmethod
    def empty(cls, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> "GaussianParams":
        z = lambda *s: torch.zeros(s, device=device, dtype=dtype)  # noqa: E731
        return cls(z(0, 3), z(0, 3), z(0, 4), z(0), z(0, 3))

    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,  # [N, 3] metres
        colors: torch.Tensor,  # [N, 3] in [0, 1]
        scales: torch.Tensor,  # [N] or [N, 3] metres (isotropic when [N])
        opacity: float = 0.5,
    ) -> "GaussianParams":
        """New isotropic-or-axis-aligned Gaussians at `points` with the given colour, size and opacity."""
        n = points.shape[0]
        if scales.dim() == 1:
            scales = scales[:, None].expand(n, 3)
        quats = torch.zeros(n, 4, dtype=points.dtype, device=points.device)
        quats[:, 0] = 1.0
        logit = torch.full((n,), float(np.log(opacity / (1.0 - opacity))), dtype=points.dtype, device=points.device)
        return cls(points.clone(), torch.log(scales.clamp_min(1e-8)).clone(), quats, logit, colors.clone().to(points.dtype))

    # ---- views in the rasteriser's parametrisation ----------------------------------------------------------

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> torch.Tensor:  # [N, 3] linear
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:  # [N] in (0, 1)
        return torch.sigmoid(self.logit_opacities)

    def tensors(self) -> list[torch.Tensor]:
        return [getattr(self, n) for n in _PARAM_NAMES]

    def map(self, fn) -> "GaussianParams":
        """A new GaussianParams with `fn` applied to every tensor (e.g. `.detach()`, `.to(device)`)."""
        return GaussianParams(*(fn(getattr(self, n)) for n in _PARAM_NAMES))

    def detached(self) -> "GaussianParams":
        return self.map(lambda t: t.detach().clone())

    def select(self, keep: torch.Tensor) -> "GaussianParams":
        """Subset by a boolean mask [N] or an index tensor."""
        return self.map(lambda t: t[keep].detach().clone())

    @staticmethod
    def concat(parts: list["GaussianParams"]) -> "GaussianParams":
        parts = [p for p in parts if p is not None]
        if not parts:
            return GaussianParams.empty()
        return GaussianParams(*(torch.cat([getattr(p, n).detach() for p in parts], dim=0) for n in _PARAM_NAMES))

    def requires_grad_(self, flag: bool = True) -> "GaussianParams":
        for t in self.tensors():
            t.requires_grad_(flag)
        return self

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.tensors())


def quat_wxyz_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of [..., 4] wxyz quaternions (torch, broadcasting)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def transform_params(params: GaussianParams, T: np.ndarray) -> GaussianParams:
    """Apply the rigid transform T [4, 4] (new frame <- old frame) to every Gaussian (eq. 15).

    means: R mu + t; covariances R Sigma R^T, i.e. the rotation quaternion left-multiplied (scales unchanged);
    opacities and colours unchanged. Returns new detached tensors; the input is not modified.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"transform_params: expected a finite 4x4 rigid transform, got shape {list(T.shape)}")
    dev, dt = params.means.device, params.means.dtype
    R = torch.as_tensor(T[:3, :3], dtype=dt, device=dev)
    t = torch.as_tensor(T[:3, 3], dtype=dt, device=dev)
    q = torch.as_tensor(se3.matrix_to_quat_wxyz(T[:3, :3]), dtype=dt, device=dev)
    with torch.no_grad():
        means = params.means @ R.T + t
        quats = quat_wxyz_multiply(q.expand_as(params.quats), params.quats)
    return GaussianParams(means, params.log_scales.detach().clone(), quats,
                          params.logit_opacities.detach().clone(), params.colors.detach().clone())


class Submap:
    """One submap: Gaussians in the local frame of its first keyframe, and where that frame sits in the world.

    `keyframe_ids` are indices into the agent's keyframe list, in insertion order (the first is the anchor).
    A finished submap may keep its Gaussians elsewhere (`stored`: compact bytes in memory or in the run folder,
    `GaussianMap.retire`); reading `params` then decodes them, and assigning `params` holds them in memory again.
    Moving a submap changes `T_world_local` only and never reads its Gaussians.
    """

    def __init__(self, id: int, T_world_local: np.ndarray, params: GaussianParams,
                 keyframe_ids: list[int] | None = None, T_world_local_no_lc: np.ndarray | None = None):
        self.id = id
        self.T_world_local = T_world_local  # [4, 4]
        self._params: GaussianParams | None = params
        self.stored: StoredGaussians | None = None
        self.keyframe_ids: list[int] = [] if keyframe_ids is None else keyframe_ids
        # Where the frame would be without loop closure: the previous submap's tracking-only frame composed with
        # this frame's offset from it at creation (pure tracking). Loop closure never changes it.
        self.T_world_local_no_lc = T_world_local_no_lc

    @property
    def params(self) -> GaussianParams:
        if self._params is None:
            return self.stored.load()
        return self._params

    @params.setter
    def params(self, value: GaussianParams) -> None:
        self._params, self.stored = value, None

    def store(self, stored: "StoredGaussians") -> None:
        """Keep the Gaussians only as `stored` (written already) and drop them from memory."""
        self._params, self.stored = None, stored

    def __len__(self) -> int:
        return self.stored.n if self._params is None else len(self._params)

    def __setstate__(self, state: dict) -> None:
        if "params" in state:  # pickled before finished submaps could be stored: the Gaussians themselves
            state["_params"] = state.pop("params")
        state.setdefault("stored", None)
        self.__dict__.update(state)

    def __repr__(self) -> str:
        where = "in memory" if self._params is not None else repr(self.stored)
        return f"Submap(id={self.id}, {len(self)} Gaussians {where}, keyframes={self.keyframe_ids})"

    def world_params(self) -> GaussianParams:
        """The submap's Gaussians moved to the world frame (eq. 2 / 15)."""
        return transform_params(self.params, self.T_world_local)


class StoredGaussians:
    """A finished submap's Gaussians kept as bytes by `store` (anything with `read(key) -> bytes`: in memory,
    or files in the run folder) under `key`, `n` of them, decoded by `decode(bytes, source=...)` on each read.
    The last one read stays decoded (`_CACHE`), so reading one submap's Gaussians view after view decodes once.
    Pickles as the store's reference, the key and the count."""

    def __init__(self, store, key: int, n: int, decode):
        self.store, self.key, self.n, self.decode = store, int(key), int(n), decode

    def load(self) -> GaussianParams:
        hit = _CACHE.get("last")
        if hit is not None and hit[0] is self.store and hit[1] == self.key:
            return hit[2]
        params = self.decode(self.store.read(self.key), source=self.store.describe(self.key))
        _CACHE["last"] = (self.store, self.key, params)
        return params

    def __repr__(self) -> str:
        return f"stored in {self.store.describe(self.key)}"


_CACHE: dict = {}  # "last": (store, key, GaussianParams) of the last stored submap decoded


class GaussianMap:
    """All submaps of one agent. Only the active submap (the last one) is optimised."""

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.submaps: list[Submap] = []
        # Where finished submaps' Gaussians go (`retire`): None keeps them in memory as they are; else an object
        # with write(key, bytes), read(key) -> bytes and describe(key) -> str, and `encode` / `decode` their form
        # (slam.dense.submap_codec).
        self.store = None
        self.encode = None
        self.decode = None

    def __len__(self) -> int:
        return sum(len(s) for s in self.submaps)

    @property
    def active(self) -> Submap:
        if not self.submaps:
            raise InputError("GaussianMap has no submap yet; call new_submap() first")
        return self.submaps[-1]

    def new_submap(self, T_world_local: np.ndarray) -> Submap:
        """Start a new (empty) active submap whose local frame is T_world_local; the previous one is frozen
        (its tensors are detached, so it holds no optimiser state or graph)."""
        T = se3.project_rigid(T_world_local)
        T_no_lc = T
        if self.submaps:
            prev = self.submaps[-1]
            prev.params = prev.params.detached()
            T_no_lc = se3.project_rigid(prev.T_world_local_no_lc @ se3.inverse(prev.T_world_local) @ T)
        s = Submap(len(self.submaps), T, GaussianParams.empty(self.device), T_world_local_no_lc=T_no_lc)
        self.submaps.append(s)
        return s

    def retire(self, submap: Submap) -> None:
        """Move a finished submap's Gaussians to `store` (encoded) and drop them from memory; nothing without a
        store or for a submap stored already."""
        if self.store is None or submap.stored is not None:
            return
        params = submap.params
        self.store.write(submap.id, self.encode(params))
        _CACHE.clear()
        submap.store(StoredGaussians(self.store, submap.id, len(params), self.decode))

    def add(self, submap: Submap, new: GaussianParams) -> int:
        """Append Gaussians (submap-local frame) to a submap; returns how many were added."""
        submap.params = GaussianParams.concat([submap.params, new.map(lambda t: t.to(self.device))])
        return len(new)

    @staticmethod
    def prune(submap: Submap, *, min_opacity: float, max_scale: float | None = None) -> int:
        """Remove Gaussians with opacity below `min_opacity` or largest axis above `max_scale` metres.

        Returns how many were removed.
        """
        p = submap.params
        with torch.no_grad():
            keep = p.opacities >= min_opacity
            if max_scale is not None:
                keep &= p.scales.max(dim=1).values <= max_scale
            keep &= torch.isfinite(p.means).all(dim=1)
        removed = int((~keep).sum())
        if removed:
            submap.params = p.select(keep)
        return removed

    @staticmethod
    def transform_submap(submap: Submap, T: np.ndarray) -> None:
        """Move a whole submap by T (world <- world): its frame and, therefore, all its Gaussians and keyframes.

        The local parameters are untouched (they live in the local frame); only `T_world_local` changes (eq. 14). The
        product is projected back onto SE(3): repeated moves must not accumulate a scale (see se3.project_rigid).
        """
        submap.T_world_local = se3.project_rigid(np.asarray(T, dtype=np.float64) @ submap.T_world_local)

    @staticmethod
    def place_submap(submap: Submap, T_world_local: np.ndarray) -> np.ndarray:
        """Put a submap's frame at T_world_local (rigid-projected); returns the move D (world <- world) applied."""
        T_new = se3.project_rigid(T_world_local)
        D = T_new @ se3.inverse(submap.T_world_local)
        submap.T_world_local = T_new
        return D

    def merged(self) -> GaussianParams:
        """Every submap's Gaussians in the world frame, concatenated (the global map, eq. 2)."""
        return GaussianParams.concat([s.world_params() for s in self.submaps if len(s)])

    def nbytes(self) -> int:
        """Bytes of the Gaussians held in memory as tensors (stored submaps not counted)."""
        return sum(s.params.nbytes() for s in self.submaps if s.stored is None)
