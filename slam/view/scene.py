"""What the viewer shows, as plain NumPy: Gaussian splats, trajectories, keyframe frusta, loop edges and a
metrics panel. Built from a run folder (slam.view.run_folder) or from a running team / agent (slam.view.state);
drawn by slam.view.server. Nothing here imports viser.

Frames: every array is in the frame named by its `frame` field: GLOBAL (agent 0's component frame for a team,
the agent's world frame for one agent), or, for a team's agents that never joined it, the name of the lowest
agent of their component (its own frame). A frame is its agent's first camera, OpenCV axes (x right, y down,
z forward), metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels import se3

# Agent colours (RGB 0-255), in agent order; loop edges and ground truth have their own colours, none of these.
AGENT_COLORS = [(31, 119, 180), (44, 160, 44), (214, 39, 40), (148, 103, 189), (23, 190, 207), (140, 86, 75),
                (188, 189, 34), (127, 127, 127)]
LOOP_COLORS = {"intra": (255, 140, 0), "inter": (230, 0, 230)}  # orange, magenta
GT_COLOR = (90, 90, 90)
GLOBAL = "global"
# The same agent's tracking-only trajectory: its colour blended this far towards white.
NO_LC_LIGHTEN = 0.55


def agent_color(i: int) -> tuple[int, int, int]:
    return AGENT_COLORS[i % len(AGENT_COLORS)]


def lighten(c: tuple[int, int, int], f: float = NO_LC_LIGHTEN) -> tuple[int, int, int]:
    return tuple(int(round(v + (255 - v) * f)) for v in c)


@dataclass
class Splats:
    """One Gaussian map: centres [N, 3] m, covariances [N, 3, 3] m², colours [N, 3] in [0, 1], opacities [N, 1]."""

    name: str
    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    frame: str = GLOBAL

    def __len__(self) -> int:
        return len(self.centers)


@dataclass
class Track:
    """A trajectory drawn as a polyline: points [N, 3] camera centres. kind: "slam" (with loop closures),
    "no_lc" (tracking only) or "gt" (ground truth)."""

    name: str
    agent: str
    kind: str
    points: np.ndarray
    color: tuple[int, int, int]
    frame: str = GLOBAL


@dataclass
class Frusta:
    """Keyframe cameras of one agent: poses [K, 4, 4] T_map_cam; fov vertical (rad), aspect width / height."""

    name: str
    agent: str
    poses: np.ndarray
    color: tuple[int, int, int]
    fov: float
    aspect: float
    frame: str = GLOBAL


@dataclass
class Edges:
    """Accepted loop closures of one kind ("intra" / "inter"): segments [M, 2, 3] between keyframe centres."""

    name: str
    kind: str
    segments: np.ndarray
    color: tuple[int, int, int]
    frame: str = GLOBAL


@dataclass
class Scene:
    title: str
    splats: list[Splats] = field(default_factory=list)
    tracks: list[Track] = field(default_factory=list)
    frusta: list[Frusta] = field(default_factory=list)
    edges: list[Edges] = field(default_factory=list)
    panel: str = ""  # Markdown
    notes: list[str] = field(default_factory=list)  # what could not be shown, and why

    def frames(self) -> list[str]:
        """GLOBAL first, then the other frames in order of appearance."""
        seen = [GLOBAL]
        for x in [*self.splats, *self.tracks, *self.frusta, *self.edges]:
            if x.frame not in seen:
                seen.append(x.frame)
        return seen

    def points(self, frame: str = GLOBAL) -> np.ndarray:
        """[M, 3] every splat centre and trajectory point in `frame` (for framing the camera)."""
        parts = [s.centers for s in self.splats if s.frame == frame]
        parts += [t.points for t in self.tracks if t.frame == frame]
        parts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in parts if len(p)]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def summary(self) -> dict:
        return {"gaussians": sum(len(s) for s in self.splats), "maps": [s.name for s in self.splats],
                "tracks": [t.name for t in self.tracks], "keyframes": sum(len(f.poses) for f in self.frusta),
                "loops": {e.kind: len(e.segments) for e in self.edges}}


def splats_from_params(name: str, params) -> Splats:
    """Splats of a slam.dense.gaussian_map.GaussianParams (log scales, wxyz quaternions, logit opacities, RGB colours):
    Σ = R diag(s²) Rᵀ, as the rasteriser builds it."""
    import torch

    with torch.no_grad():
        means = params.means.detach().double().cpu().numpy()
        scales = torch.exp(params.log_scales.detach().double()).cpu().numpy()
        quats = params.quats.detach().double().cpu().numpy()
        opac = torch.sigmoid(params.logit_opacities.detach().double()).cpu().numpy()
        rgb = params.colors.detach().double().clamp(0, 1).cpu().numpy()
    return splats_from_arrays(name, means, scales, quats, opac, rgb)


def splats_from_arrays(name: str, means: np.ndarray, scales: np.ndarray, quats_wxyz: np.ndarray,
                       opacities: np.ndarray, rgbs: np.ndarray) -> Splats:
    """means [N, 3], linear scales [N, 3], quats [N, 4] wxyz (normalised here), opacities [N] in (0, 1), rgbs [N, 3]."""
    n = len(means)
    if n == 0:
        z = np.zeros((0, 3), np.float32)
        return Splats(name, z, np.zeros((0, 3, 3), np.float32), z.copy(), np.zeros((0, 1), np.float32))
    R = se3.quat_wxyz_to_matrix(quats_wxyz)
    cov = np.einsum("nij,nj,nkj->nik", R, np.asarray(scales, np.float64) ** 2, R)
    return Splats(name, np.asarray(means, np.float32), cov.astype(np.float32),
                  np.clip(np.asarray(rgbs, np.float32), 0, 1), np.asarray(opacities, np.float32).reshape(n, 1))


def loop_edges(loops: list[tuple[str, np.ndarray, np.ndarray, str]]) -> list[Edges]:
    """Edges per kind and frame from (kind, T_frame_cam of one end [4, 4], of the other end, frame) tuples."""
    out = []
    for frame in dict.fromkeys(f for *_, f in loops):
        for kind in ("intra", "inter"):
            seg = [np.stack([a[:3, 3], b[:3, 3]]) for k, a, b, f in loops if k == kind and f == frame]
            if seg:
                out.append(Edges(f"loops_{kind}", kind, np.asarray(seg, np.float32), LOOP_COLORS[kind], frame))
    return out


def vertical_fov(camera) -> tuple[float, float]:
    """(vertical fov in radians, aspect) of a kernels.camera.PinholeCamera."""
    return 2.0 * float(np.arctan(0.5 * camera.height / camera.fy)), float(camera.width) / float(camera.height)


# A nominal camera for frusta when the run's dataset (and so its calibration) is not reachable.
NOMINAL_FOV = (np.radians(45.0), 4.0 / 3.0)


def view_from_points(pts: np.ndarray) -> dict:
    """An initial camera that sees `pts` [M, 3] (map frame, OpenCV axes so 'up' is -y): from above and behind the
    middle of the points, looking at it. Returns {"position", "look_at", "up"}."""
    if len(pts) == 0:
        return {"position": np.array([0.0, -2.0, -3.0]), "look_at": np.zeros(3), "up": np.array([0.0, -1.0, 0.0])}
    lo, hi = np.percentile(pts, 2, axis=0), np.percentile(pts, 98, axis=0)
    centre = 0.5 * (lo + hi)
    extent = max(float(np.linalg.norm(hi - lo)), 0.5)
    direction = np.array([0.0, -1.0, -0.9])  # up (-y) and back (-z) from the centre
    direction /= np.linalg.norm(direction)
    return {"position": centre + 1.1 * extent * direction, "look_at": centre, "up": np.array([0.0, -1.0, 0.0])}
