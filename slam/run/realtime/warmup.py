"""Load every kernel the stream will run before its clock starts.

The first call of a Warp or Taichi kernel loads (or compiles) its module, and torch's first operators allocate
their pools: in a fresh process the first frame and the first keyframe's mapping cost ~2 s more than later ones.
In real time that start-up falls on the stream: the tracker falls behind and drops the frames that arrive
meanwhile (a fresh `swarmsplat run --realtime --rate 15` on Redwood 211 dropped 16-20 % of its frames, most in
its first four seconds). `warm_up` runs a throwaway agent over a few frames first (tracking, a keyframe's mapping
with two iterations, its place descriptor), with a copy of the run's config, and solves a toy pose graph as loop
closure does, so the stream starts with every module loaded. It changes no state the run keeps (the agent and its map are discarded) and takes about as long as
the start-up it moves (reported as `realtime.warm_up_s`).

    from swarmsplat.slam.run.realtime.warmup import warm_up
    seconds = warm_up(camera, cfg, read, n)   # read(i) -> (color, depth) of frame i, n frames
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from swarmsplat.slam.config import SlamConfig

FRAMES = 3  # the first is a keyframe (mapping); the next are tracked against its map
ITERATIONS = 2  # mapping iterations of the throwaway keyframe: every mapping kernel runs, none for long


def warm_up(camera, cfg: SlamConfig, read, n: int) -> float:
    """Run a throwaway agent (the run's config, mapping cut to ITERATIONS) over the first min(FRAMES, n) frames,
    `read(i)` giving frame i's (color [H, W, 3] uint8, depth [H, W] or None); returns the seconds it took. The
    warm-up never stops a run: a frame it cannot read or use ends it early, silently, and the run meets that
    frame again with its own rules (a corrupt frame skipped with its reason, slam.run.guard)."""
    from swarmsplat.slam.dense.agent import Agent

    t0 = time.perf_counter()
    c = cfg.model_copy(deep=True)
    c.mapping.iterations = c.mapping.first_iterations = ITERATIONS
    agent = Agent(camera, c, name="warm-up")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(min(FRAMES, n)):
            try:
                color, depth = read(i)
                agent.step(i, float(i), np.asarray(color), None if depth is None else np.asarray(depth))
            except Exception:  # noqa: BLE001 - the run's own loop reports what is wrong with its frames
                break
        if c.loop_closure.enabled:
            _pose_graph()
    return time.perf_counter() - t0


def _pose_graph() -> None:
    """Solve a three-keyframe pose graph as loop closure does (incrementally and whole): the first solve imports
    GTSAM and the graph package, ~0.1 s that holds the interpreter's lock and, on the mapping worker during the
    stream, stalled the tracker for as long (a frame dropped at the first loop on Redwood 211 at 15 Hz)."""
    from swarmsplat.slam.dense.loops.incremental import IncrementalGraph
    from swarmsplat.slam.dense.loops.loop_closure import Edge, optimise_pose_graph

    step = np.eye(4)
    step[0, 3] = 0.1
    poses = {0: np.eye(4), 1: step, 2: step @ step}
    odometry = [Edge(0, 1, step, np.eye(6)), Edge(1, 2, step, np.eye(6))]
    loops = [Edge(0, 2, step @ step, np.eye(6))]
    try:
        IncrementalGraph().solve(poses, odometry, loops, 0)
        optimise_pose_graph(poses, odometry, loops, fixed=0)
    except Exception:  # noqa: BLE001 - a warm-up never stops a run; the stream's own solves report their errors
        pass
