"""Newton steps for the se-sync objective: the curvature term Gauss–Newton leaves out, as per-pose HessianFactors.

The SE-Sync cost is quadratic in the embedded poses, f = 1/2 sum_e kappa ||R_i R_ij - R_j||_F^2 + tau ||R_i t_ij +
t_i - t_j||^2 (GTSAM's error of the FrobeniusBetweenFactors), so its Euclidean Hessian is exactly J^T J: what
Gauss–Newton already has. What GN lacks is the curvature of the manifold: with T_i <- T_i Exp(xi), xi = [w, v]
(gtsam.Pose3.retract), T Exp(xi) = T (I + xi^ + 1/2 xi^ xi^ + O(|xi|^3)), and the second-order term adds
    1/2 <G_i, T_i xi^ xi^> = 1/2 ( w^T (sym(A) - tr(A) I) w - w^T [b]x v ),  A = R_i^T G_R,  b = R_i^T g_t,
where (G_R, g_t) is the Euclidean gradient of f with respect to (R_i, t_i). This is a 6x6 block per pose, so
Newton's model is GTSAM's linearisation plus one HessianFactor per pose (indefinite away from a minimum: the LM
loop then damps). Plain GN converges only linearly on this cost (measured on sphere2500: 7 GN/LM iterations to
a relative decrease of 1e-5, 28 to 1e-8, each shrinking the gap by ~0.7); with the term it converges quadratically.
3D only (Pose2's retract in GTSAM is not its exponential map); graphs without scale variables.
"""

from __future__ import annotations

import gtsam
import numpy as np

from swarmsplat.kernels.se3 import hat

from .formulations import Problem
from .information import diagonal_weights, se_sync_weights


NEWTON_FROM = 1e-2  # relative decrease of the last step below which Newton's step is tried first


class FrobeniusCurvature:
    """The curvature term of `problem` (se-sync objective, 3D) at given Values, edges weighted by `weights`."""

    def __init__(self, problem: Problem, weights: dict[int, float] | None = None):
        g = problem.graph
        keys = np.array(g.keys(), dtype=np.uint64)
        odo = [e for e in g.edges if e.kind == "odometry"]
        w_odo = se_sync_weights(odo) if odo else np.zeros((0, 2))
        rows = [(e.key_i, e.key_j, e.T_ij, k, t) for e, (k, t) in zip(odo, w_odo)]
        for lf in problem.loops:
            w = 1.0 if weights is None else weights.get(lf.edge, 1.0)
            if w > 0:
                k, t = diagonal_weights(w * lf.info)
                rows.append((lf.key_i, lf.key_j, lf.measured.matrix(), k, t))
        self.keys = keys
        self.ii = np.searchsorted(keys, np.array([r[0] for r in rows], dtype=np.uint64))
        self.jj = np.searchsorted(keys, np.array([r[1] for r in rows], dtype=np.uint64))
        M = np.stack([r[2] for r in rows])
        self.Rm, self.tm = M[:, :3, :3], M[:, :3, 3]
        self.kappa = np.array([r[3] for r in rows])
        self.tau = np.array([r[4] for r in rows])
        self.zero = np.zeros(6)

    def error(self, values: gtsam.Values) -> float:
        return 0.0  # the cost itself is in the factor graph

    def blocks(self, values: gtsam.Values) -> np.ndarray:
        """[N, 6, 6] per-pose curvature Hessians (module docstring), in Values' (sorted key) order."""
        X = gtsam.utilities.extractPose3(values)
        R, t = X[:, :9].reshape(-1, 3, 3), X[:, 9:]
        Ri, ti, tj = R[self.ii], t[self.ii], t[self.jj]
        dR = Ri @ self.Rm - R[self.jj]
        dt = np.einsum("eab,eb->ea", Ri, self.tm) + ti - tj
        kdR, tdt = self.kappa[:, None, None] * dR, self.tau[:, None] * dt
        GR = np.zeros_like(R)
        gt = np.zeros_like(t)
        np.add.at(GR, self.ii, kdR @ np.swapaxes(self.Rm, 1, 2) + tdt[:, :, None] * self.tm[:, None, :])
        np.add.at(GR, self.jj, -kdR)
        np.add.at(gt, self.ii, tdt)
        np.add.at(gt, self.jj, -tdt)
        A = np.swapaxes(R, 1, 2) @ GR
        b = np.einsum("nba,nb->na", R, gt)  # R^T g_t
        H = np.zeros((len(R), 6, 6))
        H[:, :3, :3] = 0.5 * (A + np.swapaxes(A, 1, 2)) - np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        B = hat(b)
        H[:, :3, 3:] = -0.5 * B
        H[:, 3:, :3] = 0.5 * B
        return H

    def linear_factors(self, values: gtsam.Values) -> list:
        H = self.blocks(values)
        return [gtsam.HessianFactor(int(k), H[n], self.zero, 0.0) for n, k in enumerate(self.keys)]


def newton_lm(problem: Problem, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, weights,
              max_iterations: int, relative_tol: float, absolute_tol: float, lambda_first: float = 1.0):
    """Minimise `graph` (the problem's se-sync factors, weighted by `weights`) from `values`. Each iteration
    linearises once and tries, in order, until one decreases the cost: the Newton step (GTSAM's linearisation +
    the curvature term; only once the previous step decreased the cost by less than NEWTON_FROM relative: far
    from the minimum Newton's model is often indefinite and Cholesky refuses it), the Gauss-Newton step, GN
    damped by lambda I, lambda = lambda_first * 10^k up to 1e10. Stops (converged) on GTSAM's tests: absolute
    decrease <= absolute_tol or relative decrease <= relative_tol, or when no step decreases the cost.
    Returns (values, iterations, initial error, final error, converged)."""
    from .solvers import _damped

    term = FrobeniusCurvature(problem, weights)
    dims = [(int(k), 6) for k in term.keys]
    err = e0 = graph.error(values)
    ordering = None
    it = 0
    try_newton = False  # from the second iteration on, once the cost decreases by less than NEWTON_FROM
    for it in range(1, max_iterations + 1):
        gfg = graph.linearize(values)
        if ordering is None:
            ordering = gtsam.Ordering.ColamdGaussianFactorGraph(gfg)

        def newton(gfg=gfg, values=values):
            out = gtsam.GaussianFactorGraph()
            out.push_back(gfg)
            for f in term.linear_factors(values):
                out.push_back(f)
            return out

        candidates = [newton, lambda: gfg] if try_newton else [lambda: gfg]
        candidates += [lambda lam=lambda_first * 10.0**k: _damped(gfg, dims, lam) for k in range(11)]
        accepted = None
        for make in candidates:
            try:
                delta = make().optimize(ordering)
            except RuntimeError:  # indefinite (Newton away from a minimum) or singular: next candidate
                continue
            new = values.retract(delta)
            new_err = graph.error(new)
            if np.isfinite(new_err) and new_err <= err:
                accepted = (new, new_err)
                break
        if accepted is None:
            return values, it, e0, err, True  # no step decreases the cost: at a minimum to machine precision
        decrease = err - accepted[1]
        values, err = accepted
        try_newton = decrease < NEWTON_FROM * (err + decrease)
        if decrease <= absolute_tol or decrease <= relative_tol * (err + decrease):
            return values, it, e0, err, True
    return values, it, e0, err, False
