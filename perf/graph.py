"""Pose-graph solve times on FLOCC's synthetic team graph: scale formulations against built-in-only LM."""

from __future__ import annotations

import statistics
import time

DESCRIPTION = ("solve time of the FLOCC team graph (6 robots, ~3,500 poses, 2,000 up-to-scale loops; --quick: "
               "1,500 poses, 600 loops): IS/SS/shared LM and GNC against GTSAM's LM on the same graph of built-in "
               "factors (base formulation), and against one gtsam.CustomFactor per loop")


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import gtsam

    from swarmsplat.graph.formulations import build_problem, initial_scales
    from swarmsplat.graph.synthetic import TeamConfig, make_team
    from swarmsplat.graph.solvers import custom_loop_factors, gnc, levenberg_marquardt
    from .common import time_fn
    from .flocc_experiment import scaled_initial_poses

    cfg = TeamConfig(length_m=250.0, target_loops=600, grid_nodes=3) if quick else TeamConfig()
    team = make_team(cfg)
    g = team.graph
    P = scaled_initial_poses(g, initial_scales(g, "odometry"))
    problems = {f: build_problem(g, f, "odometry", initial_poses=P) for f in ("base", "is", "ss", "shared")}
    repeat = 2 if quick else 3
    rows = []

    def add(case, impl, loops_as, fn, reps=repeat, peer=None):
        box, cpu = {}, []

        def call():
            c0 = time.process_time()
            box["res"] = fn()
            cpu.append(time.process_time() - c0)

        t = time_fn(call, repeat=reps, warmup=0, max_seconds=60)
        res = box["res"]
        it = res.iterations if hasattr(res, "iterations") else res[1]
        err = res.final_error if hasattr(res, "final_error") else res[2]
        row = {"case": case, "implementation": impl, "loops as": loops_as, "iterations": it,
               "median_s": t["median_s"], "cpu_s": statistics.median(cpu), "runs": t["runs"], "final_error": err}
        if peer is not None:
            row["x built-in LM"] = t["median_s"] / peer
        rows.append(row)
        return t["median_s"]

    peer = add("LM (base)", "GTSAM C++ LM", "BetweenFactorPose3", lambda: levenberg_marquardt(problems["base"]))
    rows[-1]["x built-in LM"] = 1.0
    for f, name in (("is", "IS-LM"), ("ss", "SS-LM"), ("shared", "shared-LM")):
        add(name, "our LM loop + GTSAM linear solve", "NumPy batch", lambda f=f: levenberg_marquardt(problems[f]),
            peer=peer)
    add("IS-LM", "our LM loop + GTSAM linear solve", "CustomFactor (Python-held Values)",
        lambda: levenberg_marquardt(problems["is"], loops="custom"), peer=peer)

    def gtsam_lm_custom(max_iterations):
        pr = problems["is"]
        nfg = pr.builtin_graph()
        nfg.push_back(custom_loop_factors(pr))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        opt = gtsam.LevenbergMarquardtOptimizer(nfg, pr.initial, params)
        r = opt.optimize()
        return None, opt.iterations(), nfg.error(r)

    if quick:
        add("IS-LM", "GTSAM C++ LM, 1 iteration only", "CustomFactor (Values copied per call)",
            lambda: gtsam_lm_custom(1), reps=1, peer=peer)
    else:
        add("IS-LM", "GTSAM C++ LM", "CustomFactor (Values copied per call)", lambda: gtsam_lm_custom(100),
            reps=1, peer=peer)
    for f, name in (("base", "GNC (base)"), ("is", "IS-GNC"), ("ss", "SS-GNC")):
        add(name, "our GNC (TLS) over the LM above", "as above", lambda f=f: gnc(problems[f]), reps=1, peer=peer)
    if not quick:
        def gtsam_gnc():
            pr = problems["base"]
            nfg = pr.builtin_graph()
            params = gtsam.GncLMParams()
            params.setKnownInliers(list(range(pr.fixed.size())))  # builtin_graph: fixed factors first, then loops
            opt = gtsam.GncLMOptimizer(nfg, pr.initial, params)
            r = opt.optimize()
            return None, -1, nfg.error(r)

        add("GNC (base)", "GTSAM GncLMOptimizer", "BetweenFactorPose3", gtsam_gnc, reps=1, peer=peer)
    n_loops = len(g.loops())
    notes = [f"graph: {len(g.poses)} poses, {n_loops} inter-robot loops ({len(team.outliers)} outliers), "
             f"odometry-scale initialisation, chordal initial poses; kernels backends not used (GTSAM, CPU)",
             "'x built-in LM' = median time / median time of GTSAM's LM on the base graph, same process; cpu_s = "
             "process CPU time per solve (all threads), which a shared machine's load does not inflate",
             "final_error: GTSAM's 0.5 sum of squared whitened residuals; our GNC rows of the final weighted graph, "
             "GTSAM's GNC row of the unweighted graph at its solution (its weights are not exposed the same way); "
             "iterations of GNC rows = inner LM iterations summed",
             "CustomFactor under GTSAM's LM: pybind11 copies the whole Values for every callback because LM's "
             "Values are C++-owned; the same CustomFactors evaluated on Python-held Values are not copied"]
    cols = ["case", "implementation", "loops as", "iterations", "median_s", "cpu_s", "runs", "x built-in LM",
            "final_error"]
    return {"rows": rows, "columns": cols, "notes": notes}
