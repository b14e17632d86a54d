"""Figures written next to results (PNG, matplotlib's Agg canvas: no display, no global pyplot state)."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from swarmsplat.kernels.fileio import atomic_path

_AXES = "xyz"


def plot_trajectories(path: str | Path, gt: Mapping[str, np.ndarray], est: Mapping[str, np.ndarray], *,
                      errors: Mapping[str, np.ndarray] | None = None, title: str = "", dpi: int = 110) -> Path:
    """Plot estimated (aligned) against ground-truth positions, one colour per agent, and write a PNG atomically.

    gt, est: agent name -> positions [N, 3] in metres, in the ground-truth frame. The left panel projects onto
    the two world axes along which the ground truth spreads most (top-down for a ground robot); the right
    panel, drawn when `errors` (name -> [N] metres) is given, shows the per-pose ATE along each trajectory.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    every = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in (*gt.values(), *est.values())])
    a, b = sorted(np.argsort(np.ptp(every, axis=0))[-2:]) if len(every) else (0, 1)
    fig = Figure(figsize=(11, 5) if errors else (6, 5.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if errors else 1, 1)
    colors = [f"C{k % 10}" for k in range(max(len(gt), len(est)))]
    names = list(dict.fromkeys([*gt, *est]))
    for k, name in enumerate(names):
        c = colors[k % len(colors)]
        tag = f" ({name})" if len(names) > 1 else ""
        if name in gt:
            g = np.asarray(gt[name]).reshape(-1, 3)
            # One agent: grey ground truth so the estimate stands out; several: one hue per agent.
            ax.plot(g[:, a], g[:, b], "--", color=c if len(names) > 1 else "0.35", lw=1.2, alpha=0.8,
                    label=f"ground truth{tag}")
        if name in est:
            e = np.asarray(est[name]).reshape(-1, 3)
            ax.plot(e[:, a], e[:, b], "-", color=c, lw=1.6, label=f"estimate{tag}")
            if len(e):
                ax.plot(e[:1, a], e[:1, b], "o", color=c, ms=5)
    ax.set_xlabel(f"{_AXES[a]} [m]")
    ax.set_ylabel(f"{_AXES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title or "trajectory")
    if errors:
        ax2 = fig.add_subplot(1, 2, 2)
        for k, name in enumerate(names):
            if name in errors:
                ax2.plot(np.asarray(errors[name]), color=colors[k % len(colors)], lw=1.2, label=name)
        ax2.set_xlabel("matched pose")
        ax2.set_ylabel("ATE [m]")
        ax2.grid(True, alpha=0.3)
        if len(errors) > 1:
            ax2.legend(fontsize=8)
        ax2.set_title("absolute position error")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return Path(path)
