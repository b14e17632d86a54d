"""`swarmsplat graph solve IN... --out OUT.g2o [--solver lm|gnc] [--init best|chordal|gtsam|file]
[--objective g2o|se-sync] [--information repair|isotropic|strict] [--json OUT.json] [--distributed]`.

Reads one or more g2o files, a folder of one g2o per robot (DGS) or a folder of DPGO's robotN/measurements.csv
(graph.team_files: several robots' files are merged, the two copies of an inter-robot edge must agree), replaces
information matrices that are not positive definite by the `--information` policy (graph.information; one
warning line counts them; `strict` refuses the file), initialises every connected component (default `best`:
GTSAM's InitializePose3 and our chordal initialisation, the one with the lower objective kept; ours where
GTSAM's fails), solves with Levenberg–Marquardt (GTSAM's, its default tolerances unless tighter ones are given)
or GNC, and writes the optimised graph as g2o (atomically) plus a JSON summary (default: OUT with suffix .json).
Printed and in the JSON: initial and final error (GTSAM's 0.5 * sum of squared whitened residuals of the chosen
objective), LM iterations and whether the tolerances were met, SE-Sync's cost F of the result, times. A 2D (SE2)
input is written back as 3D g2o (z, roll and pitch 0). With `--distributed` every robot solves its own part
(graph.distributed, robots simulated in one process) from the same initial estimate; the JSON adds `distributed`
(robots, rounds, bytes sent, bytes per separator pose per round, what gathering the graph on one robot would
send, the connected groups). With GNC, `rejected_loops` lists [robot_src, pose_src, robot_dst, pose_dst].
"""

from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("graph", help="pose-graph tools (solve a g2o file)")
    gsub = p.add_subparsers(dest="graph_command", metavar="ACTION", required=True)
    s = gsub.add_parser("solve", help="optimise a g2o pose graph and write the result")
    s.add_argument("inputs", nargs="+", metavar="IN",
                   help="g2o file(s), several merged (one per robot); or one folder of <k>.g2o (DGS) or of "
                        "robotN/measurements.csv (DPGO)")
    s.add_argument("--out", required=True, help="output g2o file")
    s.add_argument("--json", default=None, metavar="OUT.json", help="summary JSON (default: --out with .json)")
    s.add_argument("--solver", choices=["lm", "gnc"], default="lm", help="Levenberg-Marquardt or GNC (TLS)")
    s.add_argument("--init", choices=["best", "chordal", "gtsam", "file"], default="best",
                   help="initial poses per connected component: the better of GTSAM's InitializePose3 and our "
                        "chordal initialisation (best, default), one of them, or the file's vertices")
    s.add_argument("--objective", choices=["g2o", "se-sync"], default="g2o",
                   help="g2o: full information matrices, geodesic error (GTSAM's, default); se-sync: SE-Sync's "
                        "chordal cost with isotropic weights (reaches SE-Sync's published optima)")
    s.add_argument("--information", choices=["repair", "isotropic", "strict"], default="repair",
                   help="non-positive-definite information matrices: the nearest positive-definite matrix where "
                        "that changes it by <= 5%%, else SE-Sync's isotropic weights of its diagonal blocks (repair, "
                        "default); the isotropic weights always (isotropic); or refuse the file (strict)")
    s.add_argument("--gnc-probability", type=float, default=0.99,
                   help="GNC inlier threshold as a chi-square probability (default 0.99)")
    s.add_argument("--max-iterations", type=int, default=500, help="LM iterations at most (default 500)")
    s.add_argument("--relative-tol", type=float, default=1e-5, help="LM relative decrease tolerance (GTSAM: 1e-5)")
    s.add_argument("--absolute-tol", type=float, default=1e-5, help="LM absolute decrease tolerance (GTSAM: 1e-5)")
    s.add_argument("--distributed", action="store_true",
                   help="every robot solves its own part, exchanging separator estimates (robots simulated in one "
                        "process)")
    s.add_argument("--max-rounds", type=int, default=300, help="--distributed: rounds at most (default 300)")
    s.add_argument("--processes", action="store_true",
                   help="--distributed: one process per robot over Zenoh on this machine, a fixed number of rounds "
                        "(--max-rounds; with --solver gnc, GNC on a fixed plan: --gnc-steps)")
    s.add_argument("--gnc-steps", type=int, default=None, metavar="S",
                   help="--distributed --solver gnc: GNC on a fixed plan the robots follow themselves (what "
                        "--processes runs; default there 25): --gnc-ls-rounds rounds of least squares, the initial mu "
                        "relayed for as many rounds as there are robots, S steps of mu of --gnc-rounds rounds each, "
                        "--max-rounds rounds with the final weights. Without it the simulated team stops each phase "
                        "when it is still")
    s.add_argument("--gnc-rounds", type=int, default=4, metavar="R",
                   help="--distributed --solver gnc: rounds per GNC step at most (default 4)")
    s.add_argument("--gnc-ls-rounds", type=int, default=10, metavar="L",
                   help="--distributed --solver gnc: rounds of least squares (every weight 1) before GNC's initial "
                        "mu is taken from the residuals (default 10)")
    s.add_argument("--port-base", type=int, default=17600,
                   help="--processes: robot K listens on TCP port PORT_BASE + K (default 17600)")
    s.add_argument("--relax", type=float, default=0.0,
                   help="--distributed: over-relaxation of each robot's step, 1 to 1.9 (1: every round lowers the "
                        "cost; default 0: each robot adapts it to its observed rate of convergence)")
    s.add_argument("--sparse-tol", type=float, default=None, metavar="TOL",
                   help="--distributed: a separator pose that moved less than TOL radians and TOL times the "
                        "robot's median edge length since the neighbour's copy is not sent (default 1e-3; 0 sends "
                        "every pose every round)")
    s.set_defaults(func=run)


def run(args) -> int:
    import json
    import time
    from pathlib import Path

    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.g2o import repaired_edges, write_g2o
    from swarmsplat.graph.init import initialize
    from swarmsplat.graph.metrics import se_sync_cost
    from swarmsplat.graph.pose_graph import key_index, key_robot, key_str
    from swarmsplat.graph.solvers import gnc, levenberg_marquardt
    from swarmsplat.graph.team_files import read_team
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import atomic_write_text

    if args.max_iterations < 1 or not (args.relative_tol > 0 and args.absolute_tol > 0):
        raise InputError("--max-iterations must be >= 1 and the tolerances > 0")
    if args.relative_tol > 1e-5 or args.absolute_tol > 1e-5:
        print("warning: tolerances looser than GTSAM's defaults (1e-5): LM may stop short of the minimum",
              file=sys.stderr)
    if args.distributed and not (args.max_rounds >= 1 and (args.relax == 0.0 or 1.0 <= args.relax < 2.0)):
        raise InputError("--max-rounds must be >= 1 and --relax in [1, 2) or 0 (adaptive)")
    if args.sparse_tol is not None and not (args.distributed and 0.0 <= args.sparse_tol < 0.1):
        raise InputError("--sparse-tol applies to --distributed and must be in [0, 0.1)")
    if args.processes and not args.distributed:
        raise InputError("--processes runs the distributed solver: add --distributed")
    if args.gnc_steps is not None and not (args.distributed and args.solver == "gnc"):
        raise InputError("--gnc-steps plans the distributed GNC: add --distributed --solver gnc")
    if (args.gnc_steps is not None and args.gnc_steps < 1) or min(args.gnc_rounds, args.gnc_ls_rounds) < 1:
        raise InputError("--gnc-steps, --gnc-rounds and --gnc-ls-rounds must be >= 1")
    t_start = time.perf_counter()
    graph = read_team(args.inputs, information=args.information)
    fixed = repaired_edges(graph)
    n_fixed = sum(fixed.values())
    if n_fixed:
        how = ", ".join(f"{n} {'nearest positive-definite' if k == 'repair' else 'isotropic'}"
                        for k, n in sorted(fixed.items()))
        print(f"warning: {n_fixed} of {len(graph.edges) + len(graph.pending)} edges have an information matrix that "
              f"is not positive definite; replaced ({how}; --information strict refuses them)", file=sys.stderr)
    poses, init = initialize(graph, args.init, args.objective)
    problem = build_problem(graph, "base", initial_poses=poses, objective=args.objective)
    lm = dict(max_iterations=args.max_iterations, relative_tol=args.relative_tol, absolute_tol=args.absolute_tol)
    dist = None
    if args.distributed:
        from swarmsplat.graph.distributed.robot import Settings
        from swarmsplat.graph.distributed.team import solve_distributed

        settings = Settings(objective=args.objective, relax=args.relax)
        if args.sparse_tol is not None:
            settings.sparse_tol = args.sparse_tol
        if args.solver == "gnc" and (args.processes or args.gnc_steps is not None):
            settings.gnc_plan = _gnc_plan(args, graph)
        if args.processes:
            res = dist = _solve_processes(args, graph, poses, settings, problem)
        else:
            res = dist = solve_distributed(graph, settings, args.solver, initial_poses=poses,
                                           max_rounds=args.max_rounds, probability=args.gnc_probability,
                                           gnc_rounds=args.gnc_rounds, ls_rounds=args.gnc_ls_rounds)
    elif args.solver == "gnc":
        res = gnc(problem, probability=args.gnc_probability, lm_max_iterations=args.max_iterations)
    else:
        res = levenberg_marquardt(problem, **lm)
    out = write_g2o(graph, args.out, res.poses)
    F = se_sync_cost(graph, res.poses)
    total = time.perf_counter() - t_start
    chosen = ", ".join(f"{m} {n}" for m, n in sorted(init.chosen().items()))
    print(f"poses {len(graph.poses)}  edges {len(graph.edges)}  loops {len(graph.loops())}  "
          f"components {len(graph.components())}")
    print(f"information {args.information}  replaced {n_fixed}")
    print(f"init {args.init}  components initialised by: {chosen or 'file'}  time {init.time_s:.3f} s")
    for c in init.components[:5]:
        errs = "  ".join(f"{m} {v:.9g}" for m, v in c["errors"].items())
        fail = f"  (gtsam failed: {c['gtsam_failure']})" if c["gtsam_failure"] else ""
        print(f"  component at {key_str(c['anchor'])}: {c['poses']} poses, initial {args.objective} error {errs}"
              f" -> {c['chosen']}{fail}")
    if dist is not None:
        print(f"solver distributed {args.solver}  objective {args.objective}  robots {dist.robots}  rounds "
              f"{dist.rounds}  converged {'yes' if dist.converged else 'no'}  time {dist.time_s:.3f} s")
        print(f"bytes {dist.bytes_total}  per separator pose and round {dist.bytes_per_separator_iteration:.1f}  "
              f"elected-robot gather {dist.gather_bytes}  groups {len(dist.groups)}")
    else:
        print(f"solver {res.solver}  objective {args.objective}  iterations {res.iterations}  "
              f"converged {'yes' if res.converged else 'no'}  time {res.time_s:.3f} s")
    print(f"initial error {res.initial_error:.9g}")
    print(f"final error {res.final_error:.9g}")
    print(f"se-sync cost {F:.9g}")
    if not res.converged and dist is None:
        print(f"warning: LM stopped at --max-iterations {args.max_iterations} before meeting its tolerances",
              file=sys.stderr)
    rejected = [_loop_ids(graph.edges[n], key_robot, key_index) for n in res.rejected]
    tls = None
    if args.solver == "gnc":  # what GNC minimises: comparable between solutions that reject different loops
        from swarmsplat.graph.formulations import pose_values
        from swarmsplat.graph.solvers import inlier_threshold, tls_objective

        tls = tls_objective(problem, pose_values(res.poses, graph.is_2d),
                            inlier_threshold(args.gnc_probability, graph.is_2d))
        print(f"truncated-least-squares objective {tls:.9g}")
        names = ", ".join(f"{a}.{i}-{b}.{j}" for a, i, b, j in rejected)
        print(f"rejected loops {len(rejected)}" + (f": {names}" if names else ""))
    undecided = sum(1 for w in (dist.weights.values() if dist is not None else []) if 1e-4 < w < 1 - 1e-4)
    if undecided and args.solver == "gnc":
        print(f"warning: {undecided} loops' GNC weights are still between 0 and 1 (counted rejected below 0.5): "
              f"more GNC steps (--gnc-steps) let them settle", file=sys.stderr)
    summary = {
        "inputs": [str(p) for p in args.inputs], "out": str(out), "poses": len(graph.poses),
        "edges": len(graph.edges), "loops": len(graph.loops()), "components": len(graph.components()),
        "information": {"policy": args.information, "replaced": n_fixed, "by_rule": fixed},
        "init": {"method": args.init, "chosen": init.chosen(), "time_s": init.time_s,
                 "components": init.components},
        "solver": args.solver, "objective": args.objective,
        "iterations": dist.rounds if dist else res.iterations, "converged": res.converged,
        "relative_tol": args.relative_tol, "absolute_tol": args.absolute_tol, "max_iterations": args.max_iterations,
        "initial_error": res.initial_error, "final_error": res.final_error, "se_sync_cost": F,
        "solve_time_s": res.time_s, "total_time_s": total,
    }
    if dist is not None:
        summary["distributed"] = {
            "robots": dist.robots, "iterations": dist.rounds, "bytes_total": dist.bytes_total,
            "bytes_per_separator_iteration": dist.bytes_per_separator_iteration,
            "gather_bytes": dist.gather_bytes, "relax": args.relax, "sparse_tol": settings.sparse_tol,
            "processes": args.processes,
            "groups": [[_robot_number(chr(r)) for r in grp] for grp in dist.groups],
            "error_per_round": dist.history}
        if args.solver == "gnc":
            summary["distributed"]["undecided_loops"] = undecided
        if settings.gnc_plan is not None:
            from dataclasses import asdict

            summary["distributed"]["gnc_plan"] = asdict(settings.gnc_plan)
    if args.solver == "gnc":
        summary["tls_objective"] = tls
        summary["rejected_loops"] = rejected
    js = Path(args.json) if args.json else Path(out).with_suffix(".json")
    if js.resolve() == Path(out).resolve():
        js = Path(str(out) + ".json")
    atomic_write_text(js, json.dumps(summary, indent=1, default=float) + "\n")
    print(f"wrote {args.out}, {js}")
    return 0


def _robot_number(c: str | None) -> int:
    """DPGO's robot number of a Symbol character ('a' -> 0); a plain-integer graph is robot 0."""
    return 0 if c is None else ord(c) - ord("a")


def _loop_ids(edge, key_robot, key_index) -> list[int]:
    """[robot_src, pose_src, robot_dst, pose_dst] of a loop, as DPGO's measurement files name it."""
    return [_robot_number(key_robot(edge.key_i)), key_index(edge.key_i),
            _robot_number(key_robot(edge.key_j)), key_index(edge.key_j)]


def _gnc_plan(args, graph):
    """The fixed GNC plan of --gnc-steps / --processes (graph.distributed.gnc_plan)."""
    from swarmsplat.graph.distributed.gnc_plan import GncPlan
    from swarmsplat.graph.distributed.partition import partition
    from swarmsplat.graph.solvers import inlier_threshold

    return GncPlan(ls_rounds=args.gnc_ls_rounds, relay_rounds=len(partition(graph)), steps=args.gnc_steps or 25,
                   step_rounds=args.gnc_rounds, final_rounds=args.max_rounds,
                   barc=inlier_threshold(args.gnc_probability, graph.is_2d))


def _solve_processes(args, graph, poses, settings, problem):
    """--processes: the robots as processes (slam.run.swarm_processes.solve_graph_processes), their estimates
    gathered for the output, summarised like the simulated team's result."""
    import tempfile

    from swarmsplat.graph.distributed.partition import partition
    from swarmsplat.graph.distributed.team import DistributedResult, gather_bytes, problem_error
    from swarmsplat.graph.pose_graph import key_robot
    from swarmsplat.kernels.errors import GraphError
    from swarmsplat.slam.run.swarm_processes import solve_graph_processes

    rounds = settings.gnc_plan.total if settings.gnc_plan is not None else args.max_rounds
    with tempfile.TemporaryDirectory(prefix="swarmsplat-graph-") as work:
        out = solve_graph_processes(args.inputs, work, initial_poses=poses, settings=settings, rounds=rounds,
                                    information=args.information, port_base=args.port_base)
    if not out["finished"]:
        raise GraphError("no robot process finished")
    missing = [chr(r) for r in out["robots"] if r not in out["finished"]]
    if missing:
        print(f"warning: robot(s) {', '.join(missing)} did not finish: their initial poses are written",
              file=sys.stderr)
    est = {k: out["poses"].get(k, poses[k]) for k in graph.poses}
    weights = out["weights"] if settings.gnc_plan is not None else {}
    err = problem_error(problem, est, out["scales"], weights)
    sent = out["bytes_total"]
    groups = [sorted({ord(key_robot(k)) for k in c}) for c in graph.components()]
    separators = sum(len(s) for p in partition(graph).values() for s in p.separators.values())
    rejected = sorted(n for n, w in weights.items() if w < 0.5)
    return DistributedResult(est, out["scales"], weights, rejected, rounds, [err], [sent],
                             problem_error(problem, poses, {}, {}), err, sent, separators * (rounds + 1),
                             gather_bytes(graph),
                             len(out["robots"]), groups, not missing, out["time_s"])
