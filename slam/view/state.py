"""A Scene from a run in progress: a slam.run.team.Team or a slam.dense.agent.Agent as they are now (the live view).

Team: each component's merged map, every agent's trajectory with loop closures (in its component's frame) and
tracking only (anchored at its first pose), keyframe frusta at their current global poses, accepted loops.
Agent: its merged map, trajectory, keyframes and accepted loops, in its world frame.
"""

from __future__ import annotations

import numpy as np

from .scene import GLOBAL, Frusta, Scene, Track, agent_color, lighten, loop_edges, splats_from_params, vertical_fov


def scene_from_state(state, title: str = "swarmsplat: live") -> Scene:
    """Dispatch on what the run hands its observer: a Team (has .server) or an Agent."""
    return scene_from_team(state, title) if hasattr(state, "server") else scene_from_agent(state, title)


def scene_from_team(team, title: str = "swarmsplat: live") -> Scene:
    srv = team.server
    names = [ag.name for ag in team.agents]
    scene = Scene(title=title)
    frame = [GLOBAL if s.component == 0 else names[s.component] for s in srv.slots]  # per agent
    for root in sorted(srv.components()):
        params = srv.display_map(root)
        if len(params):
            name = "map" if root == 0 else f"map_{names[root]}"
            scene.splats.append(splats_from_params(name, params))
            scene.splats[-1].frame = frame[root]
    for a, ag in enumerate(team.agents):
        c = agent_color(a)
        _, T = team.trajectory(a)
        if len(T):
            scene.tracks.append(Track(f"{ag.name}_slam", ag.name, "slam", T[:, :3, 3], c, frame[a]))
            _, T0 = team.trajectory_no_lc(a)
            if len(T0):
                T0 = (T[0] @ np.linalg.inv(T0[0]))[None] @ T0
                scene.tracks.append(Track(f"{ag.name}_no_lc", ag.name, "no_lc", T0[:, :3, 3], lighten(c), frame[a]))
        if ag.keyframes:
            poses = np.stack([srv.global_pose(a, kf) for kf in ag.keyframes])
            scene.frusta.append(Frusta(f"keyframes_{ag.name}", ag.name, poses, c, *vertical_fov(ag.camera),
                                       frame[a]))
    index = {n: a for a, n in enumerate(names)}
    loops = []
    for r in srv.records:
        if not r.accepted:
            continue
        qa, ma = index.get(r.query_agent), index.get(r.match_agent)
        if qa is None or ma is None:
            continue
        kq, km = team.agents[qa].keyframes, team.agents[ma].keyframes
        if r.query_kf < len(kq) and r.match_kf < len(km):
            loops.append((r.kind, srv.global_pose(qa, kq[r.query_kf]), srv.global_pose(ma, km[r.match_kf]),
                          frame[qa]))
    scene.edges = loop_edges(loops)
    frames = sum(team.frames_done)
    acc = {k: sum(r.accepted and r.kind == k for r in srv.records) for k in ("intra", "inter")}
    scene.panel = (f"**running**: round {team.rounds + 1}, {frames} frames, "
                   f"{sum(len(ag.keyframes) for ag in team.agents)} keyframes, "
                   f"{sum(len(ag.gmap) for ag in team.agents)} Gaussians  \n"
                   f"loops accepted: {acc['intra']} intra, {acc['inter']} inter of {len(srv.records)} candidates  \n"
                   f"separate frames: {len(srv.components())}")
    return scene


def scene_from_agent(agent, title: str = "swarmsplat: live") -> Scene:
    scene = Scene(title=title)
    params = agent.display_map()
    if len(params):
        scene.splats.append(splats_from_params("map", params))
    c = agent_color(0)
    _, T = agent.trajectory()
    if len(T):
        scene.tracks.append(Track(f"{agent.name}_slam", agent.name, "slam", T[:, :3, 3], c))
    if agent.keyframes:
        poses = agent.keyframe_world_poses()
        scene.frusta.append(Frusta(f"keyframes_{agent.name}", agent.name, poses, c, *vertical_fov(agent.camera)))
        loops = [("intra", poses[lc.query_kf], poses[lc.match_kf], GLOBAL) for lc in agent.loops.log
                 if lc.accepted and lc.query_kf < len(poses) and lc.match_kf < len(poses)]
        scene.edges = loop_edges(loops)
    scene.panel = (f"**running**: {len(agent.poses)} frames tracked, {len(agent.keyframes)} keyframes, "
                   f"{len(agent.gmap.submaps)} submaps, {len(agent.gmap)} Gaussians, "
                   f"{sum(lc.accepted for lc in agent.loops.log)} loops accepted")
    return scene
