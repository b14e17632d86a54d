"""slam.dense.loops.loop_check: the residuals of many loops at once are each loop's residual."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.slam.dense.loops.loop_check import justified_move, loop_residuals, residual, worst_violation


def _pose(rng) -> np.ndarray:
    return se3.exp(np.concatenate([rng.normal(0, 0.5, 3), rng.normal(0, 2.0, 3)]))


def test_batched_residuals_are_each_loops_residual():
    rng = np.random.default_rng(3)
    poses = {k: _pose(rng) for k in range(40)}
    loops = []
    for _ in range(300):
        i, j = (int(x) for x in rng.integers(0, 40, 2))
        noise = se3.exp(np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 0.05, 3)]))
        loops.append((i, j, se3.inverse(poses[i]) @ poses[j] @ noise))
    got = loop_residuals(poses, loops)
    assert [r.index for r in got] == list(range(300))
    for r, (i, j, T) in zip(got, loops):
        t, d = residual(poses[i], poses[j], T)
        assert r.trans_m == pytest.approx(t, rel=1e-9, abs=1e-12) and r.rot_deg == pytest.approx(d, rel=1e-9, abs=1e-9)
    assert loop_residuals(poses, []) == []
    # the worst loop by the larger of its two ratios
    scores = [max(r.trans_m / 0.1, r.rot_deg / 2.0) for r in got]
    assert worst_violation(poses, loops, 0.1, 2.0).index == int(np.argmax(scores))
    assert justified_move(poses, [], 3.0, 0.05) == pytest.approx(0.05)
