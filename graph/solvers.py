"""Levenberg–Marquardt and GNC (truncated least squares) for `graph.formulations.Problem`s.

Where the time went with one `gtsam.CustomFactor` per loop under GTSAM's LevenbergMarquardtOptimizer (39-52 s
for 2,000 loops on ~3,500 poses, against <1 s here). GTSAM's python CustomFactor calls back into Python with
`(const CustomFactor&, const Values&, JacobianVector*)`. pybind11 converts a `const T&` callback argument with
the `copy` policy *unless that C++ object is already owned by a Python object*, in which case it hands over the
existing wrapper. Called from Python (`graph.linearize(values)` with a Values Python holds) there is no copy: 10 µs
per callback measured. Inside `LevenbergMarquardtOptimizer.optimize()` the Values being evaluated are GTSAM's
own internal copies, unknown to Python, so every callback deep-copies the whole Values: 0.5-0.6 ms per call with
5,500 variables (= `gtsam.Values(values)` measured alone), i.e. O(variables) per factor call. The callbacks
themselves are cheap. Batching loops into fewer CustomFactors would not help either: a factor's keys become one
dense clique for elimination. So:

  * graphs of built-in factors only (base formulation, metric loops, g2o files) run GTSAM's C++
    LevenbergMarquardtOptimizer;
  * graphs with scale variables (IS / SS / shared) run `_python_lm`, an LM loop in Python whose Values are always
    Python-held: the built-in part is linearised by GTSAM in C++ (`NonlinearFactorGraph.linearize`), the
    up-to-scale loops either all at once in NumPy (`loops="numpy"`, default: `scale_factors.is_residuals`, the
    same maths as the CustomFactor, tested equal) appended as JacobianFactors, or as the CustomFactors
    themselves (`loops="custom"`: no Values copy, one Python callback per loop). GTSAM's multifrontal Cholesky
    solves each step (COLAMD ordering computed once). Lambda starts at 0 (a Gauss-Newton step: anchors and the
    weak scale priors make the system positive definite); damping factors are built only when a step fails.
    Stopping tests are GTSAM's (relative and absolute decrease).
  * GNC (TLS, Yang et al. 2020, the weight update and schedule of GTSAM's GncOptimizer) is our own outer loop
    over either LM, since GTSAM's GncLMOptimizer refuses CustomFactors. By default it warm-starts every inner
    solve from the previous result (GTSAM restarts from the initial values each time, most of its run time) and
    initialises mu from the residuals of the least-squares solution, as the GNC paper does (GTSAM uses the
    initial values); `gtsam_schedule=True` restores both GTSAM choices.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.stats import chi2

from swarmsplat.kernels.errors import GraphError, InputError

from .formulations import Problem, between_factor
from .scale_factors import is_loop_factor, is_residuals, is_residuals_network

SCALE_MIN = 1e-3
# First damping after a failed Gauss-Newton step. Information here is 1e1..1e5 per unit (m, rad, scale), so
# GTSAM's 1e-5 start would take ~6 failed solves to matter; each solve is the expensive part of an iteration.
LAMBDA_FIRST = 1.0  # scales are projected back above this after each step (a negative scale flips a loop)


@dataclass
class SolveResult:
    values: gtsam.Values
    poses: dict[int, np.ndarray]  # key -> T_world_kf [4, 4]
    scales: dict[int, float]  # up-to-scale loop edge index -> optimised scale
    iterations: int  # LM iterations (GNC: summed over its inner solves)
    initial_error: float
    final_error: float  # GTSAM's 0.5 * sum of squared whitened residuals (GNC: of the final weighted graph)
    time_s: float
    solver: str
    weights: dict[int, float] = field(default_factory=dict)  # loop edge index -> GNC weight
    rejected: list[int] = field(default_factory=list)  # loop edge indices GNC rejected (weight < 0.5)
    gnc_iterations: int = 0
    converged: bool = True  # False: LM stopped at max_iterations before its tolerances were met


# ------------------------------------------------------------------------------------------- scale term
class _ScaleTerm:
    """Up-to-scale loops of a problem evaluated against gtsam.Values, all at once."""

    def __init__(self, problem: Problem, weights: dict[int, float] | None):
        sl = problem.scale_loops
        self.sl = sl
        self.pose_keys = np.array(problem.graph.keys(), dtype=np.uint64)  # Values' Pose3 order (sorted)
        self.ii = np.searchsorted(self.pose_keys, sl.key_i)
        self.jj = np.searchsorted(self.pose_keys, sl.key_j)
        self.scale_keys = sorted(set(int(k) for k in sl.key_s))
        pos = {k: n for n, k in enumerate(self.scale_keys)}
        self.ss = np.array([pos[int(k)] for k in sl.key_s])
        w = np.ones(len(sl.edge)) if weights is None else np.array([weights.get(int(n), 1.0) for n in sl.edge])
        self.sqrt_w = np.sqrt(w)
        self.active = w > 0
        self.fn = is_residuals_network if sl.residual == "network" else is_residuals

    def state(self, values: gtsam.Values):
        X = gtsam.utilities.extractPose3(values)  # [N, 12]: row-major R, then t
        T = np.zeros((len(X), 4, 4))
        T[:, :3, :3] = X[:, :9].reshape(-1, 3, 3)
        T[:, :3, 3] = X[:, 9:]
        T[:, 3, 3] = 1.0
        s = np.array([values.atDouble(k) for k in self.scale_keys])
        return T, s

    def costs(self, values: gtsam.Values) -> np.ndarray:
        """Unweighted 0.5 ||R e||² per loop [L]."""
        T, s = self.state(values)
        e = self.fn(T[self.ii], T[self.jj], s[self.ss], self.sl.R_meas, self.sl.t_meas, jacobians=False)
        r = np.einsum("lab,lb->la", self.sl.sqrt_info, e)
        return 0.5 * np.einsum("la,la->l", r, r)

    def error(self, values: gtsam.Values) -> float:
        return float(np.sum(self.sqrt_w**2 * self.costs(values)))

    def linear_factors(self, values: gtsam.Values) -> list[gtsam.JacobianFactor]:
        T, s = self.state(values)
        e, Hi, Hj, Hs = self.fn(T[self.ii], T[self.jj], s[self.ss], self.sl.R_meas, self.sl.t_meas)
        W = self.sl.sqrt_info * self.sqrt_w[:, None, None]
        Ai, Aj = W @ Hi, W @ Hj
        As = np.einsum("lab,lb->la", W, Hs)[:, :, None]
        b = -np.einsum("lab,lb->la", W, e)
        unit = gtsam.noiseModel.Unit.Create(6)
        sl = self.sl
        return [gtsam.JacobianFactor(int(sl.key_i[n]), Ai[n], int(sl.key_j[n]), Aj[n], int(sl.key_s[n]), As[n],
                                     b[n], unit) for n in np.flatnonzero(self.active)]


# ------------------------------------------------------------------------------------------- LM
def levenberg_marquardt(problem: Problem, *, weights: dict[int, float] | None = None,
                        initial: gtsam.Values | None = None, max_iterations: int = 100,
                        relative_tol: float = 1e-5, absolute_tol: float = 1e-5, loops: str = "numpy",
                        newton: bool | None = None) -> SolveResult:
    """Solve `problem` (loops weighted by `weights`, edge index -> w, default 1) from `initial` (default: the
    problem's). GTSAM's C++ LM when every factor is built-in, `_python_lm` otherwise, with the up-to-scale
    loops evaluated in NumPy (`loops="numpy"`) or as gtsam.CustomFactors (`loops="custom"`). A 3D problem with
    the se-sync objective runs graph.newton's Newton/GN steps instead (`newton=None`: whenever it applies;
    False: GTSAM's LM). Tolerances: GTSAM's relative / absolute decrease tests (its defaults 1e-5)."""
    if loops not in ("numpy", "custom"):
        raise InputError(f"loops must be 'numpy' or 'custom', got {loops!r}")
    t0 = time.perf_counter()
    values = problem.initial if initial is None else initial
    graph = problem.builtin_graph(weights)
    use_newton = problem.objective == "se-sync" and not problem.is_2d and problem.scale_loops is None
    if newton and not use_newton:
        raise InputError("newton steps need a 3D problem with the se-sync objective and no scale variables")
    if use_newton and newton is not False:
        from .newton import newton_lm

        result, iters, e0, e1, ok = newton_lm(problem, graph, values, weights, max_iterations, relative_tol,
                                              absolute_tol)
        res = _result(problem, result, iters, e0, e1, t0, "lm")
        res.converged = ok
        return res
    if problem.scale_loops is None:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_tol)
        params.setAbsoluteErrorTol(absolute_tol)
        e0 = graph.error(values)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        res = _result(problem, result, opt.iterations(), e0, graph.error(result), t0, "lm")
        res.converged = opt.iterations() < max_iterations
        return res
    term = _ScaleTerm(problem, weights)
    if loops == "custom":
        graph.push_back(custom_loop_factors(problem, weights))
    dims = [(int(k), 1) for k in term.scale_keys] + [(int(k), 6) for k in term.pose_keys]
    result, iters, e0, e1 = _python_lm(graph, term if loops == "numpy" else None, term.scale_keys, dims, values,
                                       max_iterations, relative_tol, absolute_tol)
    res = _result(problem, result, iters, e0, e1, t0, "lm")
    res.converged = iters < max_iterations
    return res


def custom_loop_factors(problem: Problem, weights: dict[int, float] | None = None) -> gtsam.NonlinearFactorGraph:
    """The problem's up-to-scale loops as IS gtsam.CustomFactors (weights scale their information)."""
    out = gtsam.NonlinearFactorGraph()
    sl = problem.scale_loops
    if sl.residual != "metric":
        raise InputError("CustomFactor loops implement the paper's (metric) residual only")
    for n in range(len(sl.edge)):
        w = 1.0 if weights is None else weights.get(int(sl.edge[n]), 1.0)
        if w <= 0:
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = sl.R_meas[n], sl.t_meas[n]
        info = w * sl.sqrt_info[n].T @ sl.sqrt_info[n]
        out.add(is_loop_factor(int(sl.key_i[n]), int(sl.key_j[n]), int(sl.key_s[n]), T,
                               gtsam.noiseModel.Gaussian.Information(info)))
    return out


def _python_lm(graph: gtsam.NonlinearFactorGraph, term: _ScaleTerm | None, scale_keys: list[int],
               dims: list[tuple[int, int]], values: gtsam.Values, max_iterations: int, relative_tol: float,
               absolute_tol: float):
    """LM over `graph` (+ the NumPy `term` when given). Every Values here is Python-held (see module docstring)."""

    def total(v):
        return graph.error(v) + (term.error(v) if term is not None else 0.0)

    err = e0 = total(values)
    pinned: set[int] = set()  # scale keys held at SCALE_MIN (loops whose scale wants to go through zero)
    unit1 = gtsam.noiseModel.Unit.Create(1)
    ordering = None
    lam = 0.0
    it = 0
    for it in range(1, max_iterations + 1):
        gfg = graph.linearize(values)
        if term is not None:
            for f in term.linear_factors(values):
                gfg.push_back(f)
        if pinned:  # release held scales whose cost gradient now points up (into the feasible side)
            grad = gfg.gradientAtZero()
            pinned = {k for k in pinned if grad.at(k)[0] >= 0.0}
        for k in pinned:
            gfg.push_back(_pin(k, values, unit1))
        if ordering is None:
            ordering = gtsam.Ordering.ColamdGaussianFactorGraph(gfg)
        while True:
            damped = _damped(gfg, dims, lam) if lam > 0 else gfg
            try:
                delta = damped.optimize(ordering)
            except RuntimeError as e:  # indeterminate system: damp and retry
                if lam > 1e10:
                    raise GraphError(f"LM: linear system cannot be solved ({e})") from None
                lam = max(lam * 10.0, LAMBDA_FIRST)
                continue
            new = values.retract(delta)
            hit = [k for k in _clamp_scales(new, scale_keys) if k not in pinned]
            if hit:  # projected step: hold these scales at the bound (active set) and solve again
                pinned.update(hit)
                for k in hit:
                    gfg.push_back(_pin(k, values, unit1))
                continue
            new_err = total(new)
            predicted = err - gfg.error(delta)  # decrease the linear model promises for this step
            if predicted < max(absolute_tol, relative_tol * err) and not new_err < err:
                return values, it, e0, err  # converged: no step can decrease the cost by the tolerance
            if np.isfinite(new_err) and new_err <= err:
                lam = 0.0 if lam <= LAMBDA_FIRST / 1e3 else lam / 10.0
                break
            lam = max(lam * 10.0, LAMBDA_FIRST)
            if lam > 1e10:
                return values, it, e0, err
        decrease = err - new_err
        values, err = new, new_err
        if decrease < absolute_tol or decrease < relative_tol * max(err + decrease, 1e-300) or err < 1e-12:
            break
    return values, it, e0, err


_DAMPING_CACHE: dict = {}


def _damped(gfg: gtsam.GaussianFactorGraph, dims: list[tuple[int, int]], lam: float) -> gtsam.GaussianFactorGraph:
    """gfg plus sqrt(lam) * I on every variable (GTSAM's LM damping without diagonal scaling). The damping
    factors depend only on (keys, lam) and lam takes powers of ten, so they are built once and reused."""
    key = (id(dims), lam)
    if key not in _DAMPING_CACHE:
        if len(_DAMPING_CACHE) > 32:
            _DAMPING_CACHE.clear()
        d_graph = gtsam.GaussianFactorGraph()
        sq = np.sqrt(lam)
        eye = {d: sq * np.eye(d) for d in (1, 3, 6)}
        zero = {d: np.zeros(d) for d in (1, 3, 6)}
        unit = {d: gtsam.noiseModel.Unit.Create(d) for d in (1, 3, 6)}
        for k, d in dims:
            d_graph.push_back(gtsam.JacobianFactor(k, eye[d], zero[d], unit[d]))
        _DAMPING_CACHE[key] = (dims, d_graph)  # holding dims keeps id(dims) unique while cached
    out = gtsam.GaussianFactorGraph()
    out.push_back(gfg)
    out.push_back(_DAMPING_CACHE[key][1])
    return out


def _pin(k: int, values: gtsam.Values, unit) -> gtsam.JacobianFactor:
    """Linear constraint (stiff) that moves scale k to SCALE_MIN in this step and keeps it there."""
    return gtsam.JacobianFactor(k, np.full((1, 1), 1e6), np.array([1e6 * (SCALE_MIN - values.atDouble(k))]), unit)


def _clamp_scales(values: gtsam.Values, keys: list[int]) -> list[int]:
    """Put scales below SCALE_MIN back at it; returns the keys that were below (a sign flip of s would turn the
    loop's translation around: such a loop is an outlier, GNC's to reject, not a reason to flip)."""
    hit = []
    for k in keys:
        if values.atDouble(k) < SCALE_MIN:
            values.update(k, SCALE_MIN)
            hit.append(k)
    return hit


def _result(problem: Problem, values: gtsam.Values, iters: int, e0: float, e1: float, t0: float, solver: str):
    keys = problem.graph.keys()
    T = np.tile(np.eye(4), (len(keys), 1, 1))
    if problem.is_2d:
        X = gtsam.utilities.extractPose2(values)
        c, s_ = np.cos(X[:, 2]), np.sin(X[:, 2])
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s_, s_, c
        T[:, :2, 3] = X[:, :2]
    else:
        X = gtsam.utilities.extractPose3(values)
        T[:, :3, :3] = X[:, :9].reshape(-1, 3, 3)
        T[:, :3, 3] = X[:, 9:]
    poses = dict(zip(keys, T))
    scales = {}
    if problem.scale_loops is not None:
        for n, k in zip(problem.scale_loops.edge, problem.scale_loops.key_s):
            scales[int(n)] = values.atDouble(int(k))
    return SolveResult(values, poses, scales, iters, float(e0), float(e1), time.perf_counter() - t0, solver)


# ------------------------------------------------------------------------------------------- GNC
def loop_costs(problem: Problem, values: gtsam.Values) -> dict[int, float]:
    """Unweighted 0.5 ||whitened residual||² of every loop (edge index -> cost)."""
    out = {}
    for lf in problem.loops:
        g = gtsam.NonlinearFactorGraph()
        g.add(_single(problem, lf))
        out[lf.edge] = g.error(values)
    if problem.scale_loops is not None:
        c = _ScaleTerm(problem, None).costs(values)
        out.update({int(n): float(v) for n, v in zip(problem.scale_loops.edge, c)})
    return out


def tls_objective(problem: Problem, values: gtsam.Values, barc: float) -> float:
    """The objective GNC minimises (truncated least squares): the known inliers' cost plus every loop's
    0.5 ||r||²_Omega capped at `barc`. Unlike the cost with GNC's final weights, it compares solutions that keep
    different loops (a rejected loop costs `barc`, not 0)."""
    costs = loop_costs(problem, values)
    zero = {n: 0.0 for n in costs}
    known = problem.builtin_graph(zero).error(values)
    if problem.scale_loops is not None:
        known += _ScaleTerm(problem, zero).error(values)
    return float(known + sum(min(c, barc) for c in costs.values()))


def _single(problem: Problem, lf):
    return between_factor(lf.key_i, lf.key_j, lf.measured, lf.info, problem.is_2d, problem.objective)


def inlier_threshold(probability: float, is_2d: bool) -> float:
    """GNC's largest inlier cost 0.5 ||r||²_Omega at a chi-square `probability` (GTSAM's barcSq,
    `setInlierCostThresholdsAtProbability`): residuals of 3 (2D) or 6 dimensions."""
    return 0.5 * float(chi2.ppf(probability, 3 if is_2d else 6))


def gnc(problem: Problem, *, inlier_cost: float | None = None, probability: float = 0.99, mu_step: float = 1.4,
        max_iterations: int = 100, relative_cost_tol: float = 1e-5, weights_tol: float = 1e-4,
        lm_max_iterations: int = 100, gtsam_schedule: bool = False) -> SolveResult:
    """Graduated non-convexity with the truncated-least-squares loss over the loop closures (odometry, anchors
    and scale factors are known inliers).

    inlier_cost: the largest 0.5 ||r||²_Omega of an inlier (GTSAM's barcSq); default 0.5 * chi2inv(probability,
    dim) as GTSAM's `setInlierCostThresholdsAtProbability`. Schedule, weight update and stopping tests as in
    GTSAM's GncOptimizer (Linear scheduler). `gtsam_schedule=True` also copies GTSAM's two choices this module
    otherwise changes (mu from the residuals at the initial values; every inner solve from the initial values),
    which reproduces Kimera-RPGO's expected outcomes exactly; it is much slower on large graphs.
    """
    if not 0.0 < probability < 1.0:
        raise InputError(f"gnc: probability must be in (0, 1), got {probability}")
    t0 = time.perf_counter()
    barc = float(inlier_cost) if inlier_cost is not None else inlier_threshold(probability, problem.is_2d)
    res = levenberg_marquardt(problem, max_iterations=lm_max_iterations)
    iters, e0 = res.iterations, res.initial_error
    costs = loop_costs(problem, res.values)
    ids = sorted(costs)
    weights = {n: 1.0 for n in ids}
    if not ids:
        res.time_s = time.perf_counter() - t0
        res.solver = "gnc"
        return res
    mu_costs = loop_costs(problem, problem.initial) if gtsam_schedule else costs
    c = np.array([mu_costs[n] for n in ids])
    pos = 2 * c - barc > 0
    mu = float(np.min(barc / (2 * c[pos] - barc))) if pos.any() else -1.0
    if 0 <= mu < 1e-6:
        mu = 1e-6
    prev_cost = res.final_error
    k = 0
    if mu > 0:
        for k in range(1, max_iterations + 1):
            c = np.array([costs[n] for n in ids])
            upper, lower = (mu + 1) / mu * barc, mu / (mu + 1) * barc
            with np.errstate(divide="ignore"):
                w = np.sqrt(barc * mu * (mu + 1) / np.maximum(c, 1e-300)) - mu
            w = np.where(c >= upper, 0.0, np.where(c <= lower, 1.0, np.clip(w, 0.0, 1.0)))
            weights = dict(zip(ids, w.tolist()))
            start = problem.initial if gtsam_schedule else res.values
            res = levenberg_marquardt(problem, weights=weights, initial=start, max_iterations=lm_max_iterations)
            iters += res.iterations
            cost = res.final_error
            costs = loop_costs(problem, res.values)
            binary = np.all(np.abs(w - np.round(w)) <= weights_tol)
            if abs(cost - prev_cost) / max(prev_cost, 1e-7) < relative_cost_tol or binary:
                break
            mu *= mu_step
            prev_cost = cost
    res.weights = weights
    res.rejected = [n for n in ids if weights[n] < 0.5]
    res.iterations = iters
    res.initial_error = e0
    res.gnc_iterations = k
    res.solver = "gnc"
    res.time_s = time.perf_counter() - t0
    return res


def solve(problem: Problem, solver: str = "lm", **kwargs) -> SolveResult:
    """`solver` 'lm' or 'gnc' with that function's keyword arguments."""
    if solver == "lm":
        return levenberg_marquardt(problem, **kwargs)
    if solver == "gnc":
        return gnc(problem, **kwargs)
    raise InputError(f"solver must be 'lm' or 'gnc', got {solver!r}")
