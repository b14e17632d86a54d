"""Run folders for the viewer tests, written with the package's own writers (no SLAM run): the estimate is the
ground truth of a generated dataset moved by a known rigid transform, so what the viewer draws can be checked
exactly. Used by tests/test_view*.py."""

from __future__ import annotations

import numpy as np
import torch

from swarmsplat.kernels import se3

# The map frame's pose in the ground-truth frame (so estimate = inv(A_MAP) @ ground truth).
A_MAP = se3.make(se3.so3_exp(np.array([0.1, -0.3, 0.2])), np.array([0.5, -0.2, 1.0]))
# Where a tracking-only trajectory's own frame sits in the map frame (any rigid move; alignment undoes it).
B_NO_LC = se3.make(se3.so3_exp(np.array([-0.2, 0.05, 0.4])), np.array([-0.3, 0.1, 0.2]))
KF_FRAMES = (0, 2)  # frame indices of each agent's keyframes 0 and 1
RED = (1.0, 0.0, 0.0)
N_GAUSSIANS = 40  # in a team run's map.ply


def gaussians(n: int = 3, color=RED, centre=(0.0, 0.0, 2.0)):
    """n Gaussians within 0.5 m of `centre`; the first has scales (0.1, 0.2, 0.3) turned 90° about z (so
    Σ = diag(0.04, 0.01, 0.09)), the others 0.15 m."""
    from swarmsplat.slam.dense.gaussian_map import GaussianParams

    rng = np.random.default_rng(0)
    means = rng.uniform(-0.5, 0.5, (n, 3)) + np.asarray(centre)
    scales = np.full((n, 3), 0.15)
    scales[0] = (0.1, 0.2, 0.3)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    quats[0] = (np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4))
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    return GaussianParams(t(means), t(np.log(scales)), t(quats), t(np.full(n, 3.0)), t(np.tile(color, (n, 1))))


def write_team_run(out, dataset, *, joined: bool = True, with_map: bool = True) -> dict:
    """A team run folder over `dataset` (a generated multi-agent dataset). joined=False: agent_1 in its own frame
    (its own component and map_agent_1.ply). Returns {agent: estimated poses [N, 4, 4]}."""
    from swarmsplat.graph.g2o import write_g2o
    from swarmsplat.graph.pose_graph import PoseGraph, robot_key
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.jsonio import write_json
    from swarmsplat.slam.dense.loops.loop_log import LoopRecord, write_loops_csv
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.io.trajectory import write_tum

    ds = load_dataset(dataset)
    names = [s.name for s in ds.agents]
    est, g = {}, PoseGraph()
    for a, s in enumerate(ds.agents):
        T = np.linalg.inv(A_MAP)[None] @ s.gt_poses
        est[s.name] = T
        write_tum(out / "trajectories" / f"{s.name}.txt", s.timestamps, T)
        write_tum(out / "trajectories_no_lc" / f"{s.name}.txt", s.timestamps, B_NO_LC[None] @ T)
        for k, f in enumerate(KF_FRAMES):
            g.add_pose(robot_key(chr(ord("a") + a), k), T[f])
    write_g2o(g, out / "pose_graph_optimized.g2o")
    rec = lambda kind, qa, qk, ma, mk, ok: LoopRecord(kind, qa, qk, KF_FRAMES[qk], ma, mk, KF_FRAMES[mk], 0.9, ok,  # noqa: E731
                                                      "accepted" if ok else "fitness", "")
    write_loops_csv(out / "loops.csv", [rec("intra", names[0], 1, names[0], 0, True),
                                        rec("inter", names[1], 0, names[0], 1, joined),
                                        rec("inter", names[1], 1, names[0], 0, False)])
    comps = {names[0]: names} if joined else {n: [n] for n in names}
    maps = {"map.ply": [names[0]] if not joined else names}
    if with_map:  # in front of agent 0's first camera, where the trajectories are
        ahead = lambda T: T[:3, 3] + 1.5 * T[:3, 2]  # noqa: E731
        save_ply(out / "map.ply", gaussians(N_GAUSSIANS, centre=ahead(est[names[0]][0])))
        if not joined:
            save_ply(out / f"map_{names[1]}.ply", gaussians(2, (0.0, 0.0, 1.0), ahead(est[names[1]][0])))
            maps[f"map_{names[1]}.ply"] = [names[1]]
    agents = [{"name": n, "frames": len(ds.agents[i]), "ate_rmse": 0.0123 + i, "ate_rmse_no_lc": 0.0456,
               "psnr": 29.5, "in_global_frame": joined or i == 0} for i, n in enumerate(names)]
    write_json(out / "metrics.json", {"dataset": str(ds.root), "agents": agents, "ate_rmse_team": 0.0234,
                                      "psnr": 29.87, "components": comps, "maps": maps, "gaussians": N_GAUSSIANS,
                                      "loops": {"intra": {"candidates": 1, "accepted": 1},
                                                "inter": {"candidates": 2, "accepted": int(joined)}}})
    return est


def write_single_run(out, sequence) -> np.ndarray:
    """A one-agent run folder over `sequence` (a generated sequence folder). Returns the estimated poses."""
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.io.jsonio import write_json
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.io.trajectory import write_tum

    s = load_sequence(sequence)
    T = np.linalg.inv(A_MAP)[None] @ s.gt_poses
    write_tum(out / "trajectory.txt", s.timestamps, T)
    write_tum(out / "keyframes.txt", s.timestamps[list(KF_FRAMES)], T[list(KF_FRAMES)])
    (out / "loops.csv").write_text(  # the columns slam.run.sequence writes
        "query_kf,match_kf,query_frame,match_frame,similarity,accepted,reason,fitness,inlier_rmse,correction_m\n"
        "1,0,2,0,0.9,True,accepted,0.8,0.01,0.001\n1,0,2,0,0.9,False,fitness 0.1 < 0.5,0.1,0.05,0.0\n")
    save_ply(out / "map.ply", gaussians(3))
    write_json(out / "metrics.json", {"agent": s.name, "dataset": str(s.root), "frames": len(s), "ate_rmse": 0.0042,
                                      "psnr": 30.1, "loops_accepted": 1, "loop_candidates": 2})
    return T
