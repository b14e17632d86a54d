"""The browser viewer (`swarmsplat view RUN`, and `--view` on `run` / `demo`): a run's merged Gaussian map as
splats, per-agent trajectories, keyframe frusta, loop edges and metrics, drawn with viser (the `view` extra).

    scene.py       what is drawn, as NumPy (no viser)        run_folder.py  a Scene from a run folder
    state.py       a Scene from a running Team / Agent       panel.py       the metrics panel (Markdown)
    server.py      the viser server that draws a Scene       live.py        the live-view observer
    screenshot.py  headless Chromium: wait for the splats, save a PNG

Only server.py (and what uses it) imports viser; building scenes does not.
"""

from .run_folder import find_run, load_scene
from .scene import Scene

__all__ = ["Scene", "find_run", "load_scene"]
