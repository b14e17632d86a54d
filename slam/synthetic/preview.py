"""A top-down picture of a world with the agents' paths (the README's docs/world.png)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from swarmsplat.kernels.fileio import atomic_write_bytes

from .world import World

_AGENT_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#17becf"]


def plot_world(world: World, poses: list[np.ndarray], path: str | os.PathLike, *, title: str | None = None) -> Path:
    """Save a PNG: walls, furniture coloured by material, each agent's path with view directions.

    poses: per agent [N, 4, 4] T_world_cam (world z up; drawn in the x-y plane).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(7, 7 * _aspect(world)), dpi=110)
    for r in world.rooms:
        ax.add_patch(Rectangle(r.lo, r.hi[0] - r.lo[0], r.hi[1] - r.lo[1], color="#f3f1ea", zorder=0))
        name = "ABCDEFGHIJKLMNOP"[r.iy * world.config.rooms_x + r.ix] + "'" * r.copy  # A' repeats A (twin)
        ax.text((r.lo[0] + r.hi[0]) / 2, r.hi[1] - 0.35, f"room {name}", ha="center",
                va="top", fontsize=9, color="#555", zorder=6)
    mt = world.materials
    for b in sorted(world.boxes, key=lambda b: b.hi[2]):
        if b.kind in ("floor", "ceiling"):
            continue
        if b.kind == "wall":
            if b.lo[2] > 0:  # lintels over openings
                continue
            face, edge = "#333333", "#333333"
        else:
            face, edge = tuple(mt.color_a[b.material]), "#555555"
        ax.add_patch(Rectangle(b.lo[:2], b.hi[0] - b.lo[0], b.hi[1] - b.lo[1], facecolor=face, edgecolor=edge,
                               linewidth=0.6, zorder=2 if b.kind == "furniture" else 3))
    for a, T in enumerate(poses):
        c = _AGENT_COLOURS[a % len(_AGENT_COLOURS)]
        xy = T[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1], color=c, linewidth=2.0, zorder=4, label=f"agent {a}")
        ax.plot(*xy[0], marker="o", color=c, markersize=7, zorder=5)
        step = max(len(T) // 12, 1)
        fwd = T[::step, :2, 2]
        fwd = fwd / np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-9)
        ax.quiver(xy[::step, 0], xy[::step, 1], fwd[:, 0], fwd[:, 1], color=c, scale=18, width=0.004,
                  zorder=5, alpha=0.8)
    lo = np.min([r.lo for r in world.rooms], axis=0) - 0.3
    hi = np.max([r.hi for r in world.rooms], axis=0) + 0.3
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"synthetic world (seed {world.seed}): paths start at the dots, arrows show view direction",
                 fontsize=9)
    ax.legend(loc="lower right", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def _aspect(world: World) -> float:
    lo = np.min([r.lo for r in world.rooms], axis=0)
    hi = np.max([r.hi for r in world.rooms], axis=0)
    return float(np.clip((hi[1] - lo[1]) / (hi[0] - lo[0]), 0.4, 2.0))
