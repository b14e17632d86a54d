"""graph/: solvers on public benchmarks (SE-Sync, Kimera-RPGO) and on synthetic up-to-scale multi-robot graphs."""

from __future__ import annotations

import copy

import gtsam
import numpy as np
import pytest
from conftest import shared_data

from swarmsplat.graph import lie
from swarmsplat.graph.formulations import build_problem
from swarmsplat.graph.g2o import read_g2o
from swarmsplat.graph.init import chordal_initialization
from swarmsplat.graph.metrics import se_sync_cost
from swarmsplat.graph.pose_graph import robot_key
from swarmsplat.graph.solvers import custom_loop_factors, gnc, levenberg_marquardt
from swarmsplat.graph.synthetic import TeamConfig, make_team

TIGHT = dict(relative_tol=1e-10, absolute_tol=1e-12, max_iterations=200)


def _gtsam_reference(path):
    """GTSAM's own pipeline: readG2o, prior on the first pose, InitializePose3 (chordal), LM."""
    nfg, _ = gtsam.readG2o(str(path), True)
    anchored = gtsam.NonlinearFactorGraph(nfg)
    anchored.addPriorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
    init = gtsam.InitializePose3.initialize(anchored)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(TIGHT["relative_tol"])
    params.setAbsoluteErrorTol(TIGHT["absolute_tol"])
    params.setMaxIterations(TIGHT["max_iterations"])
    return nfg, gtsam.LevenbergMarquardtOptimizer(anchored, init, params).optimize()


@pytest.mark.parametrize("dataset, name, published", [
    ("se_sync_sphere2500", "sphere2500.g2o", 1.687e3),
    ("se_sync_parking_garage", "parking-garage.g2o", 1.263e0),
])
def test_se_sync_benchmarks_reach_gtsams_minimum(dataset, name, published):
    path = shared_data(dataset, name)
    g = read_g2o(path)
    res = levenberg_marquardt(build_problem(g, initial_poses=chordal_initialization(g)), **TIGHT)
    nfg, ref = _gtsam_reference(path)
    ours = gtsam.Values()
    for k, T in res.poses.items():
        ours.insert(k, gtsam.Pose3(T))
    e_ours, e_ref = nfg.error(ours), nfg.error(ref)  # the between factors only: gauge invariant
    assert e_ours == pytest.approx(e_ref, rel=1e-6)
    F = se_sync_cost(g, res.poses)  # a different objective, minimised by SE-Sync: ours is close above it
    print(f"{name}: GTSAM error {e_ours:.9g} (GTSAM's own {e_ref:.9g}); SE-Sync cost {F:.6g} vs published "
          f"optimum {published:.4g}")
    assert published * (1 - 5e-4) <= F <= published * 1.05


def test_kimera_rpgo_gnc_outcomes():
    """The expectations of Kimera-RPGO's tests/testGnc.cpp (PROVENANCE) with GTSAM's GNC schedule."""
    a = read_g2o(shared_data("kimera_rpgo_two_robot", "robot_a.g2o"))
    b = read_g2o(shared_data("kimera_rpgo_two_robot", "robot_b.g2o"))
    assert len(gnc(build_problem(a), probability=0.01, gtsam_schedule=True).rejected) == 3  # GncDefault
    assert len(gnc(build_problem(a), probability=0.99, gtsam_schedule=True).rejected) == 0  # GncHighThreshold
    ab = a.merged(b)
    assert (len(ab.poses), len(ab.edges), len(ab.loops())) == (92, 95, 5)
    assert len(gnc(build_problem(ab), inlier_cost=1.0, gtsam_schedule=True).rejected) == 5
    assert len(gnc(build_problem(ab), inlier_cost=100.0, gtsam_schedule=True).rejected) == 0
    noise_info = np.eye(6) / 0.01
    for k in (1, 2):
        ab.add_loop(robot_key("a", k), robot_key("b", k), np.eye(4), noise_info)
    inter = {n for n, e in enumerate(ab.edges) if e.inter_robot}
    res = gnc(build_problem(ab), inlier_cost=1.0, gtsam_schedule=True)
    assert len(res.rejected) == 5 and not inter & set(res.rejected)  # both inter-robot closures kept
    assert len(gnc(build_problem(ab), inlier_cost=100.0, gtsam_schedule=True).rejected) == 0


def test_graph_where_gtsam_initialisation_fails_still_solves():
    a = read_g2o(shared_data("kimera_rpgo_two_robot", "robot_a.g2o"))
    ab = a.merged(read_g2o(shared_data("kimera_rpgo_two_robot", "robot_b.g2o")))  # two robots, not linked
    nfg = gtsam.NonlinearFactorGraph()
    for name in ("robot_a.g2o", "robot_b.g2o"):
        nfg.push_back(gtsam.readG2o(str(shared_data("kimera_rpgo_two_robot", name)), True)[0])
    nfg.addPriorPose3(robot_key("a", 0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
    with pytest.raises(RuntimeError, match="Indeterminate"):
        gtsam.InitializePose3.initialize(nfg)  # the second robot has no anchor
    assert len(ab.components()) == 2
    # Both starts must reach the same minimum. With TIGHT's relative decrease test (1e-10) LM stops in this flat
    # valley 2.3e-7 and 4.6e-7 above it (after 66 and 190 steps), where a step rejected by one rounding more or
    # less on another CPU stops it elsewhere; run to a decrease at float64 rounding of the cost (1e-14) instead,
    # where the two agree to 1.2e-10 (the minimum is 40.3268243), far inside the bound.
    converged = dict(relative_tol=1e-14, absolute_tol=1e-14, max_iterations=1000)
    res = levenberg_marquardt(build_problem(ab, initial_poses=chordal_initialization(ab)), **converged)
    from_file = levenberg_marquardt(build_problem(ab), **converged)
    assert np.isfinite(res.final_error)
    assert res.final_error == pytest.approx(from_file.final_error, rel=1e-8)


@pytest.fixture(scope="module")
def small_team():
    return make_team(TeamConfig(robots=3, length_m=200, target_loops=80, outlier_fraction=0.0, seed=1,
                                grid_nodes=3))


def _positions(res, keys):
    return np.stack([res.poses[k][:3, 3] for k in keys])


def test_python_lm_equals_gtsam_lm_over_custom_factors(small_team):
    g = small_team.graph
    problem = build_problem(g, "is", "odometry")
    ours = levenberg_marquardt(problem, **TIGHT)  # NumPy-batched loops
    ours_custom = levenberg_marquardt(problem, loops="custom", **TIGHT)  # the CustomFactors, our LM loop
    nfg = problem.builtin_graph()
    nfg.push_back(custom_loop_factors(problem))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    ref = gtsam.LevenbergMarquardtOptimizer(nfg, problem.initial, params).optimize()  # GTSAM's LM
    assert ours.final_error == pytest.approx(nfg.error(ref), rel=1e-6)
    assert ours_custom.final_error == pytest.approx(nfg.error(ref), rel=1e-6)
    assert ours.final_error == pytest.approx(nfg.error(ours.values), rel=1e-9)  # same objective
    sl = problem.scale_loops
    s_ref = np.array([ref.atDouble(int(k)) for k in sl.key_s])
    assert np.allclose([ours.scales[int(n)] for n in sl.edge], s_ref, atol=1e-4)


def test_wrong_scale_loop_is_absorbed_by_is_and_ss(small_team):
    team = copy.deepcopy(small_team)
    g = team.graph
    loops = [n for n, e in enumerate(g.edges) if e.up_to_scale]
    clean = {f: levenberg_marquardt(build_problem(g, f, "odometry")) for f in ("base", "is", "ss")}
    bad = loops[len(loops) // 2]
    g.edges[bad].T_ij = g.edges[bad].T_ij.copy()
    g.edges[bad].T_ij[:3, 3] *= 5.0  # the network's unit is 5x off for this loop; eq. 6 does not know
    keys = sorted(team.gt)
    moved = {}
    for f in ("base", "is", "ss"):
        res = levenberg_marquardt(build_problem(g, f, "odometry"))
        moved[f] = np.abs(_positions(res, keys) - _positions(clean[f], keys)).max()
        if f != "base":
            assert res.scales[bad] == pytest.approx(team.gt_scales[bad] / 5.0, rel=0.5)  # rescaled toward truth
    assert moved["is"] < 0.3 * moved["base"] and moved["ss"] < 0.5 * moved["base"]


def test_wrong_rotation_loop_is_rejected_by_gnc(small_team):
    team = copy.deepcopy(small_team)
    g = team.graph
    loops = [n for n, e in enumerate(g.edges) if e.up_to_scale]
    bad = loops[5]
    g.edges[bad].T_ij = g.edges[bad].T_ij.copy()
    g.edges[bad].T_ij[:3, :3] = g.edges[bad].T_ij[:3, :3] @ lie.so3_exp(np.array([[0.0, 0.0, np.pi / 2]]))[0]
    for f in ("base", "is", "ss"):
        res = gnc(build_problem(g, f, "gt", gt_scales=team.gt_scales))
        assert bad in res.rejected
        assert len(res.rejected) <= 2


def test_the_tls_objective_caps_each_loop_at_gncs_threshold(small_team):
    """tls_objective: with every loop below the threshold it is the plain least-squares error; a loop above it
    counts the threshold, not its cost."""
    from swarmsplat.graph.solvers import loop_costs, tls_objective

    team = copy.deepcopy(small_team)
    g = team.graph
    for f in ("base", "is"):
        problem = build_problem(g, f, "gt", gt_scales=team.gt_scales)
        values = levenberg_marquardt(problem).values
        costs = loop_costs(problem, values)
        barc = 2 * max(costs.values()) + 1.0
        plain = problem.builtin_graph().error(values)
        if problem.scale_loops is not None:
            from swarmsplat.graph.solvers import _ScaleTerm

            plain += _ScaleTerm(problem, None).error(values)
        assert tls_objective(problem, values, barc) == pytest.approx(plain, rel=1e-12)
        worst = max(costs, key=costs.get)
        cut = costs[worst] / 2  # below the worst loop's cost (and maybe others')
        assert tls_objective(problem, values, cut) == pytest.approx(
            plain - sum(c - cut for c in costs.values() if c > cut), rel=1e-12)


def test_eq8_scales_shrink_with_loop_noise_and_network_residual_removes_it():
    """Why IS scales settle below the truth with inlier loops only: eq. 8 multiplies the measurement noise by s
    (regression dilution) and lets the solver pull trajectories together. Comparing in the network's unit
    reduces the bias (measured: 0.965 -> 1.02 here). Same graph, same start, noisy (0.5 m) loop translations,
    no outliers."""
    team = make_team(TeamConfig(robots=3, length_m=200, target_loops=150, outlier_fraction=0.0, seed=2,
                                grid_nodes=3, loop_sigma_trans=0.5))
    ratios = {}
    for residual in ("metric", "network"):
        res = levenberg_marquardt(build_problem(team.graph, "is", "gt", initial_poses=team.gt,
                                                gt_scales=team.gt_scales, scale_residual=residual))
        ratios[residual] = np.median([res.scales[n] / team.gt_scales[n] for n in res.scales])
    assert ratios["metric"] < 0.97  # biased low
    assert abs(ratios["network"] - 1.0) < abs(ratios["metric"] - 1.0)
