"""The distributed solver as one process per robot over Zenoh on localhost, against the simulated team.

    python -m perf distributed-processes --json perf/results/distributed-processes-cpu.json \
        --md perf/results/distributed-processes-cpu.md

A generated 8-robot metric team (graph.synthetic, written as one g2o that every robot process reads) solved by 8
robot processes (`swarmsplat graph solve --distributed --processes`: slam.run.swarm_processes.solve_graph_processes)
for a fixed number of rounds, against the simulated team on the same schedule (`solve_distributed(...,
stop_when_still=False)`), both from `graph solve`'s initial estimate: the largest difference of any pose, and
the cost against the centralised LM's. Then again with one robot process killed without a
word at mid-solve, against the simulated team whose robot leaves at that round, and the others' cost against the
centralised optimum of their parts with the lost robot held where it last was (what the others can still reach).
Last, GNC over processes: the real 6-robot outdoor graph of Kimera-Multi (../shared/data, skipped when absent) as 6
robot processes on the fixed GNC plan `graph solve --distributed --processes --solver gnc` runs
(graph.distributed.gnc_plan defaults: 10 rounds of least squares, the initial mu relayed 6 rounds, 25 steps of 4
rounds, 30 rounds with the final weights), against the simulated team on the same plan
and the centralised GNC. `--quick`: 4 robots, and no GNC case.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

DESCRIPTION = ("8 robot processes over Zenoh against the simulated team (fixed schedule), and with one killed at "
               "mid-solve")
COLUMNS = ["case", "robots", "poses", "loops", "rounds", "max_pose_diff", "finished", "error", "reference_error",
           "ratio", "rejected", "rejected_as_simulated", "bytes_total", "time_s"]


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import sys

    import numpy as np

    from swarmsplat.graph.distributed.robot import Settings
    from swarmsplat.graph.distributed.team import Faults, problem_error, solve_distributed
    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.g2o import write_g2o
    from swarmsplat.graph.init import initialize
    from swarmsplat.graph.solvers import solve
    from swarmsplat.graph.synthetic import TeamConfig, make_team
    from swarmsplat.graph.team_files import read_team
    from swarmsplat.slam.flocc.swarm.zenoh_transport import free_port_base
    from swarmsplat.slam.run.swarm_processes import solve_graph_processes

    n = 4 if quick else 8
    rounds, kill_after = 20, 10
    team = make_team(TeamConfig(robots=n, length_m=150, grid_step=30.0, grid_nodes=3, target_loops=60 * n,
                                loop_radius=8.0, outlier_fraction=0.0, seed=7))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "team.g2o"
        write_g2o(team.graph, path)
        g = read_team([path])
        base = {"robots": n, "poses": len(g.poses), "loops": len(g.loops()), "rounds": rounds}
        P0, _ = initialize(g, "best")  # as `graph solve` starts: the better of chordal and GTSAM's
        problem = build_problem(g, "base", initial_poses=P0)
        central = solve(problem, "lm").final_error

        sim = solve_distributed(g, Settings(), initial_poses=P0, max_rounds=rounds, stop_when_still=False)
        t0 = time.perf_counter()
        out = solve_graph_processes([str(path)], Path(tmp) / "all", initial_poses=P0, settings=Settings(),
                                    rounds=rounds, port_base=free_port_base(n, 24000))
        diff = max(float(np.abs(out["poses"][k] - sim.poses[k]).max()) for k in sim.poses)
        err = problem_error(problem, out["poses"], {}, {})
        rows.append({"case": "all robots", **base, "max_pose_diff": diff, "finished": len(out["finished"]),
                     "error": err, "reference_error": central, "ratio": err / central,
                     "bytes_total": out["bytes_total"], "time_s": time.perf_counter() - t0})
        print(f"[distributed-processes] all robots: max pose difference {diff:.2e}, cost / centralised "
              f"{err / central:.5f}", file=sys.stderr)

        gone = ord("a") + n // 2
        at_leave: dict = {}

        def grab(team_):
            if team_.round == kill_after:
                at_leave.update(team_.estimate()[0])

        sim = solve_distributed(g, Settings(), initial_poses=P0, max_rounds=rounds, stop_when_still=False,
                                faults=Faults(leave={gone: kill_after + 1}), on_round=grab)
        t0 = time.perf_counter()
        out = solve_graph_processes([str(path)], Path(tmp) / "kill", initial_poses=P0, settings=Settings(),
                                    rounds=rounds, port_base=free_port_base(n, 24000), crash={gone - ord("a"): kill_after})
        diff = max(float(np.abs(out["poses"][k] - sim.poses[k]).max()) for k in out["poses"])
        held = [k for k in g.keys() if k >> 56 == gone]
        others = build_problem(g, "base", initial_poses=at_leave, anchors=g.anchors() + held)
        reference = solve(others, "lm").final_error
        poses = {**{k: at_leave[k] for k in held}, **out["poses"]}
        err = problem_error(others, poses, {}, {})
        rows.append({"case": f"robot {chr(gone)} killed after round {kill_after}", **base,
                     "max_pose_diff": diff, "finished": len(out["finished"]), "error": err,
                     "reference_error": reference, "ratio": err / reference, "bytes_total": out["bytes_total"],
                     "time_s": time.perf_counter() - t0})
        print(f"[distributed-processes] robot {chr(gone)} killed: max pose difference {diff:.2e}, cost / the "
              f"others' optimum {err / reference:.5f}", file=sys.stderr)
    if not quick:
        row = _gnc_case()
        if row is not None:
            rows.append(row)
    notes = [f"rounds fixed at {rounds} (the same schedule in processes and simulated); max_pose_diff: the largest "
             "difference of any pose matrix entry between the robot processes and the simulated team",
             "killed: the process exits without a word after the round named; the simulated reference's robot leaves "
             "at the next round; reference_error: the centralised LM optimum of the others' parts with the killed "
             "robot held at its estimate when it died, ratio the processes' cost over it",
             "time_s: wall time of the robot processes (starting Python and GTSAM in each included)",
             "GNC: reference_error is the centralised GNC's cost; rejected: loops the processes reject; "
             "rejected_as_simulated: the same set as the simulated team on the same plan"]
    return {"rows": rows, "columns": COLUMNS, "notes": notes}


def _gnc_case() -> dict | None:
    """The outdoor graph's robots as processes on a fixed GNC plan, against the simulated team on it."""
    import sys

    import numpy as np
    from swarmsplat.graph.distributed.gnc_plan import GncPlan
    from swarmsplat.graph.distributed.partition import partition
    from swarmsplat.graph.distributed.robot import Settings
    from swarmsplat.graph.distributed.team import problem_error, solve_distributed
    from swarmsplat.graph.formulations import build_problem
    from swarmsplat.graph.init import initialize
    from swarmsplat.graph.solvers import inlier_threshold, solve
    from swarmsplat.graph.team_files import read_team
    from swarmsplat.slam.flocc.swarm.zenoh_transport import free_port_base
    from swarmsplat.slam.run.swarm_processes import solve_graph_processes

    from .distributed import _data

    path = _data("kimera_multi_outdoor_6robots")
    if path is None:
        return None
    g = read_team([path])
    n = len(partition(g))
    P0, _ = initialize(g, "best")
    problem = build_problem(g, "base", initial_poses=P0)
    central = solve(problem, "gnc").final_error
    plan = GncPlan(relay_rounds=n, barc=inlier_threshold(0.99, g.is_2d))  # the plan `graph solve` runs
    sim = solve_distributed(g, Settings(gnc_plan=plan), "gnc", initial_poses=P0)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = solve_graph_processes([str(path)], Path(tmp) / "gnc", initial_poses=P0,
                                    settings=Settings(gnc_plan=plan), rounds=plan.total,
                                    port_base=free_port_base(n, 24000))
    diff = max(float(np.abs(out["poses"][k] - sim.poses[k]).max()) for k in sim.poses)
    rejected = sorted(m for m, w in out["weights"].items() if w < 0.5)
    err = problem_error(problem, out["poses"], {}, out["weights"])
    print(f"[distributed-processes] GNC: max pose difference {diff:.2e}, rejected {len(rejected)} "
          f"(as simulated: {rejected == sim.rejected})", file=sys.stderr)
    return {"case": "outdoor graph, GNC plan", "robots": n, "poses": len(g.poses), "loops": len(g.loops()),
            "rounds": plan.total, "max_pose_diff": diff, "finished": len(out["finished"]), "error": err,
            "reference_error": central, "ratio": err / central, "rejected": len(rejected),
            "rejected_as_simulated": rejected == sim.rejected, "bytes_total": out["bytes_total"],
            "time_s": time.perf_counter() - t0}
