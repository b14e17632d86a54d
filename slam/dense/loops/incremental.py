"""An agent's keyframe pose graph solved incrementally (iSAM2), so that a loop closure costs what its new factors
and the part of the graph they touch cost, not a re-solve of the whole mission.

The graph is the one `loop_closure.optimise_pose_graph` solves in one batch: a prior anchoring the first keyframe,
the tracking edges between consecutive keyframes and the active loop edges, each a GTSAM BetweenFactorPose3 with
its information. `IncrementalGraph.solve` brings iSAM2 up to date with the edge lists as they stand — keyframes and
tracking edges added since the last call, loops accepted since, loops rejected since removed — and returns the
estimate. A new loop is followed by a few more iSAM2 steps, until the estimate moves less than `tolerance`, so the
result is the batch optimum to within that (tests/test_incremental_graph.py).

iSAM2 cannot be pickled. A checkpoint (slam.run.checkpoint) keeps the log of updates instead — which keyframes,
edges and loops each update added or removed, and the initial values it gave — and the unpickled graph replays
that log on its next use, which makes iSAM2 the same as the uninterrupted run's, step for step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from swarmsplat.kernels import se3

ANCHOR_SIGMA = 1e-6  # as graph.formulations anchors a component's first pose


@dataclass
class _Update:
    """One iSAM2 update as the log keeps it: new keyframe values, the tracking edges [odo_from, odo_to), the loop
    edges added and removed (indices into the loop list) and the extra steps run after it."""

    values: dict[int, np.ndarray]
    odo_from: int
    odo_to: int
    loops_added: list[int]
    loops_removed: list[int]
    steps: int = 0


@dataclass
class IncrementalGraph:
    relinearize_threshold: float = 0.001  # iSAM2: relinearise a variable whose delta exceeds this (rad / m)
    wildfire_threshold: float = 1e-5  # iSAM2: back-substitution stops where the delta changes less than this
    tolerance: float = 1e-6  # extra steps stop when no pose moves more than this (m, rad) in a step
    max_steps: int = 20  # extra steps after an update that added or removed loops, at most
    log: list[_Update] = field(default_factory=list)
    anchor: int = 0  # the keyframe the prior holds (the first solve's `fixed`)
    _isam: object = None
    _n_poses: int = 0
    _n_odometry: int = 0
    _loop_factor: dict[int, int] = field(default_factory=dict)  # loop index -> iSAM2 factor index
    _replayed: int = 0  # updates of the log applied to _isam

    def __getstate__(self) -> dict:  # iSAM2 is rebuilt from the log on the next solve
        state = dict(self.__dict__)
        state.update(_isam=None, _n_poses=0, _n_odometry=0, _loop_factor={}, _replayed=0)
        return state

    # ---- solving ---------------------------------------------------------------------------------------------

    def solve(self, initial: dict[int, np.ndarray], odometry: list, loops: list, fixed: int) -> dict[int, np.ndarray]:
        """The optimum of the graph (keyframe id -> T_world_kf) with `odometry` (Edge list, consecutive keyframes,
        appended only) and the loops of `loops` (Edge list, appended only) that are not rejected. `initial`
        gives the world pose of every keyframe now: new keyframes start there. The estimate is re-anchored so
        that keyframe `fixed` stays at its initial pose."""
        self._replay(odometry, loops)
        if not self.log:
            self.anchor = fixed
        active = {n for n, e in enumerate(loops) if not e.rejected}
        new_keys = range(self._n_poses, max(initial, default=-1) + 1)  # keyframe ids only grow
        up = _Update(values={k: np.array(initial[k]) for k in new_keys if k in initial},
                     odo_from=self._n_odometry, odo_to=len(odometry),
                     loops_added=sorted(active - set(self._loop_factor)),
                     loops_removed=sorted(set(self._loop_factor) - active))
        if up.values or up.odo_to > up.odo_from or up.loops_added or up.loops_removed:
            up.steps = self._apply(up, odometry, loops, converge=bool(up.loops_added or up.loops_removed))
            self.log.append(up)
            self._replayed = len(self.log)
        est = self._isam.calculateEstimate()
        out = {k: est.atPose3(k).matrix() for k in initial}
        D = initial[fixed] @ se3.inverse(out[fixed])  # re-anchor (the prior holds it to within ANCHOR_SIGMA)
        return {k: D @ T for k, T in out.items()}

    def _replay(self, odometry: list, loops: list) -> None:
        """Bring a fresh (unpickled) iSAM2 to the state the log describes, update by update."""
        if self._isam is None:
            self._isam = _new_isam(self.relinearize_threshold, self.wildfire_threshold)
            self._n_poses = self._n_odometry = self._replayed = 0
            self._loop_factor = {}
        if self._replayed < len(self.log):
            for up in self.log[self._replayed:]:
                self._apply(up, odometry, loops, converge=False, steps=up.steps)
            self._replayed = len(self.log)

    def _apply(self, up: _Update, odometry: list, loops: list, *, converge: bool, steps: int | None = None) -> int:
        """Run one logged update on iSAM2; returns the extra steps run (given: replay runs as many)."""
        import gtsam

        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        kinds: list[tuple[str, int]] = []
        for k, T in up.values.items():
            values.insert(k, gtsam.Pose3(T))
            if k == self.anchor:
                graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(T), gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)))
                kinds.append(("prior", k))
        for n in range(up.odo_from, up.odo_to):
            e = odometry[n]
            graph.add(_between(e))
            kinds.append(("odometry", n))
        for n in up.loops_added:
            graph.add(_between(loops[n]))
            kinds.append(("loop", n))
        removed = [self._loop_factor.pop(n) for n in up.loops_removed]
        res = self._isam.update(graph, values, removed)
        for (kind, n), index in zip(kinds, res.getNewFactorsIndices()):
            if kind == "loop":
                self._loop_factor[n] = int(index)
        self._n_poses = max([self._n_poses, *[k + 1 for k in up.values]])
        self._n_odometry = up.odo_to
        if steps is not None:
            for _ in range(steps):
                self._isam.update()
            return steps
        if not converge:
            return 0
        # The poses a new or removed loop moves most are its own ends and the newest keyframe: watch those.
        keys = sorted({k for n in up.loops_added + up.loops_removed for k in (loops[n].i, loops[n].j)}
                      | {self._n_poses - 1})
        prev = [self._isam.calculateEstimatePose3(k) for k in keys]
        done = 0
        for _ in range(self.max_steps):
            self._isam.update()
            done += 1
            now = [self._isam.calculateEstimatePose3(k) for k in keys]
            change = max(float(np.abs(gtsam.Pose3.Logmap(a.between(b))).max()) for a, b in zip(prev, now))
            if change < self.tolerance:
                break
            prev = now
        return done


def _new_isam(threshold: float, wildfire: float):
    import gtsam

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(threshold)
    params.relinearizeSkip = 1
    gn = gtsam.ISAM2GaussNewtonParams()
    gn.setWildfireThreshold(wildfire)
    params.setOptimizationParams(gn)
    return gtsam.ISAM2(params)


def _between(e):
    import gtsam

    return gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_ij), gtsam.noiseModel.Gaussian.Information(e.info))
