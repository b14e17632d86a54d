"""Load every kernel the stream will run before its clock starts.

The first call of a Warp or Taichi kernel loads (or compiles) its module, and torch's first operators allocate
their pools: in a fresh process the first frame and the first keyframe's mapping cost ~2 s more than later ones.
In real time that start-up falls on the stream: the tracker falls behind and drops the frames that arrive
meanwhile (a fresh `swarmsplat run --realtime --rate 15` on Redwood 211 dropped 10-20 % of its frames, most in
its first four seconds). `warm_up` runs a throwaway agent over a few frames first (tracking, a keyframe's mapping
with two iterations, its place descriptor), with a copy of the run's config, so the stream starts with every
module loaded. It changes no state the run keeps (the agent and its map are discarded) and takes about as long as
the start-up it moves (reported as `realtime.warm_up_s`).

    from swarmsplat.slam.run.realtime.warmup import warm_up
    seconds = warm_up(camera, cfg, frames)   # frames: [(color, depth)]
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from swarmsplat.slam.config import SlamConfig

FRAMES = 3  # the first is a keyframe (mapping); the next are tracked against its map
ITERATIONS = 2  # mapping iterations of the throwaway keyframe: every mapping kernel runs, none for long


def warm_up(camera, cfg: SlamConfig, frames) -> float:
    """Run a throwaway agent (the run's config, mapping cut to ITERATIONS) over `frames` [(color [H, W, 3] uint8,
    depth [H, W] or None)], the first FRAMES of them; returns the seconds it took. Frames it cannot use (too little
    depth) are skipped as the run skips them, silently: the run warns about its own."""
    from swarmsplat.slam.dense.agent import Agent

    t0 = time.perf_counter()
    c = cfg.model_copy(deep=True)
    c.mapping.iterations = c.mapping.first_iterations = ITERATIONS
    agent = Agent(camera, c, name="warm-up")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (color, depth) in enumerate(list(frames)[:FRAMES]):
            agent.step(i, float(i), np.asarray(color), None if depth is None else np.asarray(depth))
    return time.perf_counter() - t0
