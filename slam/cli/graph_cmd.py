"""`swarmsplat graph solve IN.g2o [IN2.g2o ...] --out OUT.g2o [--solver lm|gnc] [--init file|chordal]`.

Reads one or more g2o files (several robots' files are merged, edges present in two files kept once), solves
the pose graph with Levenberg–Marquardt or GNC, writes the optimised graph as g2o (atomically) and prints the
initial and final error (GTSAM's 0.5 * sum of squared whitened residuals) and, for GNC, the rejected loops.
A 2D (SE2) input is written back as 3D g2o (z, roll and pitch 0).
"""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("graph", help="pose-graph tools (solve a g2o file)")
    gsub = p.add_subparsers(dest="graph_command", metavar="ACTION", required=True)
    s = gsub.add_parser("solve", help="optimise a g2o pose graph and write the result")
    s.add_argument("inputs", nargs="+", metavar="IN.g2o", help="g2o file(s); several are merged (one per robot)")
    s.add_argument("--out", required=True, help="output g2o file")
    s.add_argument("--solver", choices=["lm", "gnc"], default="lm", help="Levenberg-Marquardt or GNC (TLS)")
    s.add_argument("--init", choices=["file", "chordal"], default="file",
                   help="start from the file's vertices or from a chordal initialisation (default: file)")
    s.add_argument("--gnc-probability", type=float, default=0.99,
                   help="GNC inlier threshold as a chi-square probability (default 0.99)")
    s.add_argument("--max-iterations", type=int, default=100)
    s.set_defaults(func=run)


def run(args) -> int:
    from graph.formulations import build_problem
    from graph.g2o import read_g2o, write_g2o
    from graph.init import chordal_initialization
    from graph.pose_graph import key_str
    from graph.solvers import gnc, levenberg_marquardt

    graph = read_g2o(args.inputs[0])
    for path in args.inputs[1:]:
        graph = graph.merged(read_g2o(path))
    init = chordal_initialization(graph) if args.init == "chordal" else None
    problem = build_problem(graph, "base", initial_poses=init)
    if args.solver == "gnc":
        res = gnc(problem, probability=args.gnc_probability, lm_max_iterations=args.max_iterations)
    else:
        res = levenberg_marquardt(problem, max_iterations=args.max_iterations)
    write_g2o(graph, args.out, res.poses)
    print(f"poses {len(graph.poses)}  edges {len(graph.edges)}  loops {len(graph.loops())}  "
          f"components {len(graph.components())}")
    print(f"solver {res.solver}  iterations {res.iterations}  time {res.time_s:.3f} s")
    print(f"initial error {res.initial_error:.9g}")
    print(f"final error {res.final_error:.9g}")
    if args.solver == "gnc":
        names = ", ".join(f"{key_str(graph.edges[n].key_i)}-{key_str(graph.edges[n].key_j)}" for n in res.rejected)
        print(f"rejected loops {len(res.rejected)}" + (f": {names}" if names else ""))
    print(f"wrote {args.out}")
    return 0
