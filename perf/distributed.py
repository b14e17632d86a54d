"""The distributed solver (graph.distributed) against the centralised solve of the same formulation.

    python -m perf distributed [--quick] --json perf/results/distributed-cpu.json --md perf/results/distributed-cpu.md

Cases: FLOCC's formulation study team (graph.synthetic, LIO odometry, eq.-6 scales, the chordal start of
perf/flocc_experiment; `--quick`: its 250 m-per-robot team) in the base, IS, SS and shared formulations with LM;
DGS's blocks_world with every team size present (2, 4, 9 and 16 robots in ../shared; 25, 36 and 49 where they
are added beside them) (LM) and the 6-robot outdoor graph of Kimera-Multi (GNC) from
`../shared/data`, each started from `swarmsplat graph solve`'s initial estimate (the better of chordal and GTSAM's
per component); each robot's over-relaxation adaptive (the default), a few cases again with plain descent. Per case: the centralised cost (LM, or GNC where robust),
the distributed cost and its ratio, rounds to 1 % and 0.1 % of the centralised cost, bytes sent in all and up to
1 %, bytes per separator pose per round, and what gathering the graph on one robot and broadcasting its estimate
would send (graph.distributed.team.gather_bytes). For GNC: the share of the centralised GNC's kept loops the
distributed one keeps and of its rejected loops it rejects, and both GNCs' truncated-least-squares objective.
Last (not with `--quick`), a generated 8-robot team with 3,500 inter-robot loops of which 30 % are wrong (GNC), the
stand-in for a real team's place recognition. Shared graphs that are absent are skipped.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

DESCRIPTION = ("distributed solver vs centralised (same formulation): cost ratio, rounds to 1 % / 0.1 %, bytes vs "
               "the elected-robot gather")
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
COLUMNS = ["case", "robots", "poses", "loops", "solver", "relax", "central_error", "error", "ratio", "rounds_1pct",
           "rounds_0.1pct", "rounds", "bytes_1pct", "gather_bytes", "bytes_total", "bytes_per_sep", "kept",
           "rejected", "central_tls", "tls", "time_s"]


def _data(*parts: str) -> Path | None:
    """$SWARMSPLAT_SHARED_DATA/PARTS, else ../shared/data/PARTS; None when absent (the case is skipped)."""
    roots = [Path(os.environ["SWARMSPLAT_SHARED_DATA"])] if os.environ.get("SWARMSPLAT_SHARED_DATA") else []
    for root in (*roots, DATA):
        if root.joinpath(*parts).exists():
            return root.joinpath(*parts)
    return None


def _flocc_cases(quick: bool):
    from swarmsplat.graph.formulations import initial_scales

    from .flocc_experiment import scaled_initial_poses, team_config
    from swarmsplat.graph.synthetic import make_team

    team = make_team(team_config("lio", quick))
    g = team.graph
    P0 = scaled_initial_poses(g, initial_scales(g, "odometry"))
    for form in ("base", "is", "ss", "shared"):
        yield f"flocc-{form}", g, P0, form, "lm", 0.0
    yield "flocc-is", g, P0, "is", "lm", 1.0


def _outlier_team():
    """A generated 8-robot team with 3,500 inter-robot loops, 30 % of them wrong (GNC), from the scaled start."""
    from swarmsplat.graph.formulations import initial_scales
    from swarmsplat.graph.synthetic import TeamConfig, make_team

    from .flocc_experiment import scaled_initial_poses

    g = make_team(TeamConfig(robots=8, length_m=250, target_loops=3500, outlier_fraction=0.3, seed=3)).graph
    yield "generated-8-outliers", g, scaled_initial_poses(g, initial_scales(g, "odometry")), "base", "gnc", 0.0


def _blocks_world() -> list[tuple[str, tuple[str, ...]]]:
    """DGS's blocks_world teams present in the shared data, by size (`Nrobots` folders: the repository has 2-49)."""
    root = _data("dgs_multirobot", "blocks_world")
    if root is None:
        return []
    sizes = sorted(int(d.name[:-6]) for d in root.glob("*robots") if d.name[:-6].isdigit())
    return [(f"blocks_world-{n}", ("dgs_multirobot", "blocks_world", f"{n}robots")) for n in sizes]


def _shared_cases():
    from swarmsplat.graph.init import initialize
    from swarmsplat.graph.team_files import read_team

    cases = [(name, parts, "lm") for name, parts in _blocks_world()]
    cases.append(("kimera-outdoor-6", ("kimera_multi_outdoor_6robots",), "gnc"))
    for name, parts, solver in cases:
        path = _data(*parts)
        if path is None:
            continue
        g = read_team([path])
        P0, _ = initialize(g, "best")
        yield name, g, P0, "base", solver, 0.0
        if name == "blocks_world-16":
            yield name, g, P0, "base", solver, 1.0


def measure(name, g, P0, form, solver, relax, max_rounds) -> dict:
    from swarmsplat.graph.distributed.robot import Settings
    from swarmsplat.graph.distributed.team import solve_distributed
    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.solvers import solve

    ref = solve(build_problem(g, form, initial_poses=P0), solver)
    t0 = time.perf_counter()
    res = solve_distributed(g, Settings(formulation=form, relax=relax), solver, initial_poses=P0,
                            max_rounds=max_rounds)
    row = {"case": name, "robots": res.robots, "poses": len(g.poses), "loops": len(g.loops()), "solver": solver,
           "relax": relax, "central_error": ref.final_error, "error": res.final_error,
           "ratio": res.final_error / ref.final_error, "rounds_1pct": res.rounds_to(ref.final_error, 0.01),
           "rounds_0.1pct": res.rounds_to(ref.final_error, 0.001), "rounds": res.rounds,
           "bytes_1pct": res.bytes_to(ref.final_error, 0.01), "gather_bytes": res.gather_bytes,
           "bytes_total": res.bytes_total, "bytes_per_sep": res.bytes_per_separator_iteration,
           "kept": None, "rejected": None, "central_tls": None, "tls": None, "time_s": time.perf_counter() - t0}
    if solver == "gnc":
        from swarmsplat.graph.solvers import inlier_threshold, tls_objective

        R, D = set(ref.rejected), set(res.rejected)
        kept = set(ref.weights) - R
        row["kept"] = len(kept - D) / max(len(kept), 1)
        row["rejected"] = len(R & D) / max(len(R), 1)
        problem = build_problem(g, form, initial_poses=P0)
        row["central_tls"] = tls_objective(problem, ref.values, inlier_threshold(0.99, g.is_2d))
        row["tls"] = res.tls_error
    return row


def similarity3_timing(loops: int = 2000) -> tuple[float, float]:
    """Seconds to linearise `loops` GTSAM BetweenFactorSimilarity3 against our batched IS loop residuals and
    Jacobians (graph.scale_factors.is_residuals), median of 5, on random poses."""
    import statistics

    import gtsam
    import numpy as np

    from swarmsplat.graph import lie
    from swarmsplat.graph.scale_factors import is_residuals

    rng = np.random.default_rng(0)
    T = lie.exp(rng.normal(size=(2 * loops, 6)) * 0.3)
    Ti, Tj = T[:loops], T[loops:]
    R = lie.so3_exp(rng.normal(size=(loops, 3)) * 0.1)
    t = rng.normal(size=(loops, 3))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(7, 0.1)
    for n in range(loops):
        values.insert(2 * n, gtsam.Similarity3(gtsam.Rot3(Ti[n][:3, :3]), Ti[n][:3, 3], 1.0))
        values.insert(2 * n + 1, gtsam.Similarity3(gtsam.Rot3(Tj[n][:3, :3]), Tj[n][:3, 3], 1.0))
        graph.add(gtsam.BetweenFactorSimilarity3(2 * n, 2 * n + 1, gtsam.Similarity3(gtsam.Rot3(R[n]), t[n], 1.0),
                                                 noise))

    def timed(fn):
        out = []
        for _ in range(5):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
        return statistics.median(out)

    return timed(lambda: graph.linearize(values)), timed(lambda: is_residuals(Ti, Tj, np.ones(loops), R, t))


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import sys

    rows = []
    max_rounds = 60
    for case in list(_flocc_cases(quick)) + list(_shared_cases()) + ([] if quick else list(_outlier_team())):
        row = measure(*case, max_rounds=max_rounds)
        print(f"[distributed] {row['case']} relax {row['relax']}: ratio {row['ratio']:.5f}, rounds to 1 % "
              f"{row['rounds_1pct']}, to 0.1 % {row['rounds_0.1pct']}, {row['time_s']:.1f} s", file=sys.stderr)
        rows.append(row)
    notes = [f"rounds at most {max_rounds}; a round: every robot steps once, colour by colour (neighbours never at "
             "the same time); relax 0: each robot's over-relaxation adapted to its rate of convergence (the default), "
             "1: plain block-coordinate descent (every round lowers the cost)",
             "bytes_per_sep: all bytes sent (headers, scales, weights, consensus scalars included) per separator "
             "pose sent (a pose: 12 B as a float16 twist from the estimate the neighbour holds, 24 B absolute); "
             "gather_bytes: every robot but the lowest sends its poses and owned edges, the lowest sends every pose "
             "back to each (absolute float32 poses)",
             "kept / rejected (GNC): share of the centralised GNC's kept / rejected loops the distributed GNC also "
             "keeps / rejects; central_tls / tls (GNC): the truncated-least-squares objective both GNCs minimise "
             "(every loop's cost capped at the inlier threshold), which compares solutions that reject different "
             "loops (error and ratio count a rejected loop as 0); GNC: 10 rounds of least squares, then at most 4 "
             "rounds per step of mu"]
    extra = [name for name, _ in _blocks_world() if name not in {f"blocks_world-{n}" for n in (2, 4, 9, 16)}]
    if extra:
        notes.append(f"{', '.join(extra)}: read from dgs_multirobot/blocks_world beside the shared teams, which ship "
                     "2, 4, 9 and 16 robots (DGS's repository, distributed_mapper_core/data/blocks_world/, has the "
                     "others)")
    sim3, ours = similarity3_timing()
    notes.append(f"linearising 2,000 loops: GTSAM BetweenFactorSimilarity3 {sim3 * 1e3:.1f} ms, our batched IS "
                 f"residuals and Jacobians {ours * 1e3:.1f} ms (a Sim(3) factor puts the scale on keyframes, not on "
                 "the loop: not FLOCC's formulations)")
    return {"rows": rows, "columns": COLUMNS, "notes": notes}
