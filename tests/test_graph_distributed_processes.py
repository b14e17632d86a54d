"""The distributed solver with one process per robot over Zenoh on localhost (slam.flocc.swarm.solver_node,
slam.run.swarm_processes.solve_graph_processes): the same estimates as the simulated team on the same schedule,
also when a robot dies mid-solve."""

from __future__ import annotations

import numpy as np
import pytest
from test_swarm_zenoh import _free_port_base  # the swarm's Zenoh tests' loopback port search

from swarmsplat.graph.distributed.robot import Settings
from swarmsplat.graph.distributed.team import Faults, solve_distributed
from swarmsplat.graph.g2o import write_g2o
from swarmsplat.graph.synthetic import TeamConfig, make_team
from swarmsplat.graph.team_files import read_team
from swarmsplat.slam.flocc.swarm.zenoh_transport import zenoh_available

pytestmark = [pytest.mark.skipif(not zenoh_available(), reason="eclipse-zenoh is not installed"), pytest.mark.slow]


def test_robot_processes_equal_the_simulated_team_and_survive_a_robot_dying(tmp_path):
    from swarmsplat.slam.run.swarm_processes import solve_graph_processes

    # three robots that all meet (three colours): a metric graph written as g2o, read back by every process
    team = make_team(TeamConfig(robots=3, length_m=120, grid_step=30.0, grid_nodes=2, target_loops=80,
                                loop_radius=8.0, outlier_fraction=0.0, seed=5))
    write_g2o(team.graph, tmp_path / "team.g2o")
    g = read_team([tmp_path / "team.g2o"])
    rounds = 6
    sim = solve_distributed(g, Settings(), initial_poses=g.poses, max_rounds=rounds, stop_when_still=False)
    out = solve_graph_processes([str(tmp_path / "team.g2o")], tmp_path / "w1", initial_poses=g.poses,
                                settings=Settings(), rounds=rounds, port_base=_free_port_base(3))
    assert out["finished"] == [97, 98, 99]
    assert max(np.abs(out["poses"][k] - sim.poses[k]).max() for k in sim.poses) <= 1e-6

    # robot b dies after round 3: the others wait for it once, then go on with its last estimate, exactly as the
    # simulated team whose robot b leaves at round 4
    sim = solve_distributed(g, Settings(), initial_poses=g.poses, max_rounds=rounds + 2, stop_when_still=False,
                            faults=Faults(leave={98: 4}))
    out = solve_graph_processes([str(tmp_path / "team.g2o")], tmp_path / "w2", initial_poses=g.poses,
                                settings=Settings(), rounds=rounds + 2, port_base=_free_port_base(3), crash={1: 3})
    assert out["finished"] == [97, 99]
    assert max(np.abs(out["poses"][k] - sim.poses[k]).max() for k in out["poses"]) <= 1e-6
    assert sim.history[-1] < sim.history[4]  # the others kept converging after b left


def test_robot_processes_run_the_same_gnc_as_the_simulated_team(tmp_path):
    """GNC on a fixed plan (graph.distributed.gnc_plan): each robot proposes the initial mu, relays the smallest and
    sets its loops' weights at its own step, so three robot processes reject the same loops as the simulated team
    and end at its poses."""
    from scipy.stats import chi2

    from swarmsplat.graph.distributed.gnc_plan import GncPlan
    from swarmsplat.slam.run.swarm_processes import solve_graph_processes

    team = make_team(TeamConfig(robots=3, length_m=120, grid_step=30.0, grid_nodes=2, target_loops=80,
                                loop_radius=8.0, outlier_fraction=0.1, seed=5))
    write_g2o(team.graph, tmp_path / "team.g2o")
    g = read_team([tmp_path / "team.g2o"])
    plan = GncPlan(ls_rounds=4, relay_rounds=3, steps=5, step_rounds=2, final_rounds=3,
                   barc=0.5 * float(chi2.ppf(0.99, 6)))
    sim = solve_distributed(g, Settings(gnc_plan=plan), "gnc", initial_poses=g.poses)
    assert sim.rounds == plan.total and len(sim.rejected) >= 3
    out = solve_graph_processes([str(tmp_path / "team.g2o")], tmp_path / "w", initial_poses=g.poses,
                                settings=Settings(gnc_plan=plan), rounds=plan.total, port_base=_free_port_base(3))
    assert out["finished"] == [97, 98, 99]
    assert sorted(n for n, w in out["weights"].items() if w < 0.5) == sim.rejected
    assert max(abs(out["weights"][n] - w) for n, w in sim.weights.items()) <= 1e-6
    assert max(np.abs(out["poses"][k] - sim.poses[k]).max() for k in sim.poses) <= 1e-6
