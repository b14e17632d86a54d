"""How the team server's loop-closure cost per keyframe grows with the team: 2, 4 and 8 agents, each on 30 frames
of one generated 160x120 walk through the procedural rooms (consecutive stretches, so neighbouring agents overlap
where the walk passes a place twice), the demo's tiny settings otherwise.

Reported per team size: keyframes, candidates verified per keyframe (intra and inter), the server's loop-closure
seconds per keyframe (descriptor search, registration, the cloud route, render checks; the pose-graph solve
apart), the cloud route's windows and registrations per keyframe, and the ratio of the per-keyframe cost to the
2-agent team's. The verification budget per keyframe (server.top_k, loop_closure.pose_top_k, top_k,
cloud_per_keyframe) is fixed, so the ratio should stay near 1; only the descriptor search is linear in the team's
keyframes.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

DESCRIPTION = "team server cost per keyframe for 2, 4 and 8 agents (generated)"

FRAMES_PER_AGENT = 30


def _team(root: Path, n_agents: int, frames: int) -> dict:
    from swarmsplat import kernels
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.io.datasets.split import split_sequence
    from swarmsplat.slam.run.team import Team

    seq = load_sequence(root / "agent_0")
    ds = split_sequence(seq, [(k * frames, (k + 1) * frames) for k in range(n_agents)])
    cfg = SlamConfig.preset("demo-tiny")
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    team = Team([s.camera for s in ds.agents], [s.name for s in ds.agents], cfg, cfg.server)
    t0 = time.perf_counter()
    team.run(ds.agents)
    wall = time.perf_counter() - t0
    srv = team.server
    n_kf = sum(len(a.keyframes) for a in team.agents)
    recs = srv.records
    loop_s = srv.time["intra"] + srv.time["inter"]
    st = srv.clouds.stats() if srv.clouds is not None else {"windows_built": 0, "registrations": 0}
    return {"agents": n_agents, "keyframes": n_kf,
            "candidates_per_keyframe": round(len(recs) / n_kf, 2),
            "inter_candidates_per_keyframe": round(sum(r.kind == "inter" for r in recs) / n_kf, 2),
            "loop_ms_per_keyframe": round(1000 * loop_s / n_kf, 1),
            "cloud_windows_per_keyframe": round(st["windows_built"] / n_kf, 2),
            "cloud_registrations_per_keyframe": round(st["registrations"] / n_kf, 2),
            "components": len(srv.components()), "wall_s": round(wall, 1)}


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    sizes = (2, 4) if quick else (2, 4, 8)
    frames = FRAMES_PER_AGENT
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = generate(Path(tmp) / "walk", GeneratorConfig.preset("tiny", agents=1, frames=frames * max(sizes),
                                                                    seed=7))
        for n in sizes:
            rows.append(_team(root, n, frames))
    base = rows[0]["loop_ms_per_keyframe"] or 1e-9
    for r in rows:
        r["cost_ratio_to_2"] = round(r["loop_ms_per_keyframe"] / base, 2)
    cols = ["agents", "keyframes", "candidates_per_keyframe", "inter_candidates_per_keyframe", "loop_ms_per_keyframe",
            "cost_ratio_to_2", "cloud_windows_per_keyframe", "cloud_registrations_per_keyframe", "components",
            "wall_s"]
    return {"rows": rows, "columns": cols,
            "notes": [f"{frames} frames per agent of one generated 160x120 walk (tiny generator preset, seed 7), the "
                      "demo-tiny SLAM preset; loop_ms_per_keyframe is the server's intra + inter loop-closure time "
                      "(pose-graph solves apart) over every keyframe of the team"]}
