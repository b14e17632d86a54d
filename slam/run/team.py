"""A team of GRAND-SLAM agents and the server (§III-D–E, §IV): each agent runs the per-agent pipeline (track,
submaps, map) on its own sequence; every keyframe it makes goes to the server, which closes intra- and
inter-agent loops on one multi-agent pose graph and moves the submaps (slam.dense.team.server).

The agents run in one process, round-robin one frame each, as if they recorded at the same time; an agent whose
sequence ends leaves the rotation and the others carry on. Loop closures are the server's job, so each agent's
own optimisation is switched off (it would undo the inter-agent corrections); the agent's LoopCloser still
provides descriptors, tracking edges and intra-agent verification.

    from swarmsplat.slam.run.team import run_team
    metrics = run_team("data/synth", "results/team", SlamConfig())
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import output_dir

from swarmsplat.slam.dense.agent import Agent
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.loops.loop_log import LoopRecord
from .partial_results import write_partial_team
from swarmsplat.slam.run.guard import guarded, keep, read_frame
from swarmsplat.slam.dense.team.server import Server, ServerConfig


class Team:
    """N agents and one server. `step(a, frame)` feeds agent a one frame; `run(...)` feeds whole sequences."""

    def __init__(self, cameras: Sequence, names: Sequence[str], config: SlamConfig | None = None,
                 server: ServerConfig | None = None, *, agent_class: type = Agent):
        """agent_class: what each agent is built as (slam.dense.team.mirror.AgentMirror: an agent running in
        another process, slam.run.team_link)."""
        if len(cameras) != len(names) or not names:
            raise InputError(f"a team needs one camera per agent name, got {len(cameras)} and {len(names)}")
        if len(names) > 26:
            raise InputError(f"at most 26 agents (one pose-graph letter each), got {len(names)}")
        self.cfg = config or SlamConfig()
        if server is not None:  # the server's settings given apart replace the config's `server` section
            self.cfg = self.cfg.model_copy(update={"server": server})
        scfg = self.cfg.server.model_copy()
        scfg.intra_loops = scfg.intra_loops and self.cfg.loop_closure.enabled
        scfg.inter_loops = scfg.inter_loops and self.cfg.loop_closure.enabled
        agent_cfg = self.cfg.override({"loop_closure": {"enabled": False}})  # the server optimises
        self.agents = [agent_class(c, agent_cfg, name=n) for c, n in zip(cameras, names)]
        rc = self.cfg.map_refine  # the server's map refinement fits the keyframes at the mapping resolution
        for ag in self.agents:
            ag.keep_keyframe_images = rc.views == "mapping" and rc.iterations_per_keyframe > 0 and rc.max_iterations > 0
        self.server = Server(self.agents, scfg)
        # Per agent, each submap's origin as tracking alone placed it: the trajectory without loop closures.
        self._origins_no_lc: list[list[np.ndarray]] = [[] for _ in self.agents]
        self.rounds = 0
        self.frames_done = [0] * len(self.agents)
        self.journals: list | None = None  # one slam.run.checkpoint.PoseJournal per agent (run_team sets them)

    # ---- running ---------------------------------------------------------------------------------------------

    def step(self, a: int, index: int, timestamp: float, color: np.ndarray, depth: np.ndarray | None
             ) -> list[LoopRecord]:
        """One frame of agent a; when it becomes a keyframe the server looks for loops. Returns new loop records."""
        ag = self.agents[a]
        n_kf, n_sm = len(ag.keyframes), len(ag.gmap.submaps)
        ag.step(index, timestamp, color, depth)
        self.frames_done[a] += 1
        if self.journals:
            self.journals[a].follow(ag)
        if len(ag.gmap.submaps) > n_sm:
            self._record_origin(a)
        if len(ag.keyframes) > n_kf:
            return self.server.on_keyframe(a, ag.keyframes[-1], self.rounds)
        return []

    def _record_origin(self, a: int) -> None:
        """A new submap's origin relative to the previous one is pure tracking (it is set from the active submap
        and the tracked pose); chaining those relatives gives the submap origins a run without loops would have."""
        sms = self.agents[a].gmap.submaps
        origins = self._origins_no_lc[a]
        if not origins:
            origins.append(sms[0].T_world_local.copy())
            return
        k = len(sms) - 1
        rel = se3.inverse(sms[k - 1].T_world_local) @ sms[k].T_world_local
        origins.append(origins[k - 1] @ rel)

    def run(self, sequences: Sequence, *, limits: Sequence[int] | None = None, stride: int = 1,
            progress: Callable[[int, int, str], None] | None = None, strict: bool = False, start: int = 0,
            after_round: Callable[[int], None] | None = None) -> float:
        """Feed every agent its sequence, one frame per agent per round, until all have ended. `limits[a]` caps
        agent a's input frames; `stride` k uses every k-th frame (a faster, coarser run). An unreadable frame is
        skipped with a warning (strict: raise). Returns wall seconds.
        progress: called after every round with (rounds done, rounds in all, status line); start: the first
        round (a resumed run's); after_round: called with the next round's index after every round (the run's
        checkpoints)."""
        if stride < 1:
            raise InputError(f"frame stride must be at least 1, got {stride}")
        n = _frame_counts(sequences, limits)
        rounds = -(-max(n, default=0) // stride)
        t0 = time.perf_counter()
        for i in range(start, rounds):
            self.rounds = i
            for a, seq in enumerate(sequences):
                if i * stride < n[a]:  # an agent whose sequence has ended simply leaves the rotation
                    f = read_frame(seq, i * stride, self.agents[a], strict=strict)
                    if f is not None:  # None: unreadable, skipped with a warning
                        self.step(a, f.index, f.timestamp, f.color, f.depth)
            if progress:
                progress(i + 1, rounds, self.status(i + 1, rounds, time.perf_counter() - t0))
            if after_round is not None:
                after_round(i + 1)
        return time.perf_counter() - t0

    def rounds_in(self, sequences: Sequence, limits: Sequence[int] | None, stride: int) -> int:
        """How many rounds `run` makes over these sequences."""
        return -(-max(_frame_counts(sequences, limits), default=0) // stride)

    def __getstate__(self) -> dict:  # a checkpoint pickles the team; the journals are files the run reopens
        state = dict(self.__dict__)
        state["journals"] = None
        return state

    def finish(self) -> dict | None:
        """A last global optimisation over every keyframe (those added since the last loop included)."""
        if any(r.accepted for r in self.server.records):
            return self.server.optimise()
        return None

    def refine_map(self) -> dict:
        """The server's global map refinement (config section `map_refine`; iterations_per_keyframe 0 = off)."""
        rc = self.cfg.map_refine
        if rc.iterations_per_keyframe <= 0 or rc.max_iterations <= 0:
            return {}
        return self.server.refine_maps(rc, self.cfg.mapping, self.cfg.exposure if self.cfg.exposure.enabled else None)

    def status(self, done: int, total: int, elapsed: float) -> str:
        loops = self.server.records
        acc_i = sum(r.accepted and r.kind == "intra" for r in loops)
        acc_x = sum(r.accepted and r.kind == "inter" for r in loops)
        groups = len(self.server.components())
        return (f"round {done}/{total}  keyframes {sum(len(a.keyframes) for a in self.agents)}  "
                f"Gaussians {sum(len(a.gmap) for a in self.agents)}  loops {acc_i} intra / {acc_x} inter "
                f"of {len(loops)}  separate frames {groups}  {elapsed:.0f}s")

    # ---- results ---------------------------------------------------------------------------------------------

    def trajectory(self, a: int) -> tuple[np.ndarray, np.ndarray]:
        """Agent a's frames in its component's frame, with loop closures: each frame follows the pose-graph optimum
        of its keyframe (Server.global_trajectory per_keyframe=True)."""
        return self.server.global_trajectory(a, per_keyframe=True)

    def trajectory_no_lc(self, a: int) -> tuple[np.ndarray, np.ndarray]:
        """Agent a's frames as tracking alone placed them (its own world frame)."""
        ag = self.agents[a]
        o = self._origins_no_lc[a]
        if not ag.poses:
            return np.zeros(0), np.zeros((0, 4, 4))
        return (np.array([p.timestamp for p in ag.poses]),
                np.stack([o[p.submap_id] @ p.T_local_cam for p in ag.poses]))

    def keyframe_pose_no_lc(self, a: int, kf) -> np.ndarray:
        return self._origins_no_lc[a][kf.submap_id] @ kf.T_local_cam


def _frame_counts(sequences: Sequence, limits: Sequence[int] | None) -> list[int]:
    """Input frames per agent: its sequence's length, capped by limits[a] when given (0 = no cap)."""
    return [len(s) if limits is None or not limits[a] else min(len(s), int(limits[a])) for a, s in enumerate(sequences)]


def _finished_submaps(team: Team) -> int:
    """Submaps finished (frozen) across the team."""
    return sum(len(ag.gmap.submaps) - 1 for ag in team.agents if ag.gmap.submaps)


@guarded("team")
def run_team(dataset_path: "str | Path | MultiAgentDataset", out_dir: str | Path, config: SlamConfig | None = None, *,
             server: ServerConfig | None = None, frames: int | None = None, limits: Sequence[int] | None = None,
             stride: int | None = None, progress: bool = True, render_views: int | None = None, observer=None,
             strict: bool = False, resume: bool = False) -> dict:
    """Run the team on a multi-agent RGB-D dataset (any layout `slam.io.datasets.load_dataset` reads) and write
    every output to `out_dir` (see slam.run.team_results). Returns the metrics written to metrics.json.
    `dataset_path` may also be an already loaded MultiAgentDataset (e.g. from swarmsplat.slam.io.datasets.split.split_sequence).

    server: replaces the config's `server` section (None: config.server).
    frames: at most this many input frames per agent (None: config.max_frames, 0 = all); limits: per-agent
    caps; stride: use every stride-th frame (None: config.team.stride).
    render_views: keyframes per agent rendered from the merged map for PSNR / SSIM / depth L1 (0 = all; None:
    config.team.render_views).
    observer: `observer(team)` after every round, `observer(team, force=True)` after the map refinement
    (slam.view.live.LiveView, the live view).
    strict: stop at an unreadable frame (default: skip it). An interrupt or a failure writes what was done so far
    (slam.run.partial_results.write_partial_team) and re-raises.
    As it goes the run appends each agent's keyframes' frames to out_dir/progress/<agent>.tum and checkpoints the
    whole team (config `checkpoint`: each time that many submaps have been finished across the team, and after
    the last round); resume: continue the run in `out_dir` from its last checkpoint (InputError naming what
    differs when it is not a run of this dataset and config).
    """
    from swarmsplat.kernels.fileio import atomic_write_text
    from swarmsplat.slam.io.datasets import MultiAgentDataset, load_dataset
    from swarmsplat.slam.io.progress import TeamRounds
    from .checkpoint import CHECKPOINT, PoseJournal, find_resume, save_checkpoint, team_identity
    from .runtime import check_device, use_kernels

    cfg = config or SlamConfig()
    if server is not None:  # the server's settings given apart replace the config's `server` section (as Team)
        cfg = cfg.model_copy(update={"server": server})
    stride = cfg.team.stride if stride is None else stride
    render_views = cfg.team.render_views if render_views is None else render_views
    ds = dataset_path if isinstance(dataset_path, MultiAgentDataset) else load_dataset(dataset_path)
    if ds.kind != "rgbd":
        raise InputError(f"{ds.root}: the GRAND-SLAM team needs RGB-D sequences, this dataset is {ds.kind}")
    use_kernels(cfg.kernels)  # backend, device and torch's thread count, as `swarmsplat run`
    check_device(cfg.kernels, [s.camera for s in ds.agents], cfg.image.max_width)
    cap = frames if frames is not None else cfg.max_frames
    caps = []
    for a in range(len(ds.agents)):  # the smaller of the global and the agent's own cap; 0 = no cap
        c = [int(x) for x in (cap, limits[a] if limits else None) if x]
        caps.append(min(c) if c else 0)
    out = output_dir(out_dir, "--out")
    identity = team_identity(ds, cfg, caps, stride)
    resumed = find_resume(out, identity) if resume else None
    atomic_write_text(out / "config.yaml", cfg.to_yaml())  # what --resume checks before the first checkpoint
    team = resumed.agent if resumed else Team([s.camera for s in ds.agents], [s.name for s in ds.agents], cfg)
    start = resumed.next_frame if resumed else 0
    rounds = team.rounds_in(ds.agents, caps, stride)
    if resume and progress:
        print(f"[team] resuming at round {start} of {rounds}" if resumed else
              f"[team] no checkpoint in {out} yet: starting from the first round", file=sys.stderr)
    cpu0 = time.process_time()
    t_start = time.perf_counter() - (resumed.wall_s if resumed else 0.0)  # the run's time includes the work resumed
    keep(lambda status, reason: write_partial_team(team, ds, out, status=status, reason=reason,
                                                   wall_s=time.perf_counter() - t_start,
                                                   run_info={"frame_stride": stride, "frame_caps": caps}))
    team.journals = [PoseJournal(out / "progress" / f"{ag.name}.tum",
                                 resume=resumed.journal[a] if resumed else None)
                     for a, ag in enumerate(team.agents)]
    every = cfg.checkpoint.every_submaps
    finished = _finished_submaps(team)  # at the last checkpoint

    def checkpoint(next_round: int) -> None:
        save_checkpoint(out, identity, team, next_frame=next_round, journal=[j.state() for j in team.journals],
                        wall_s=time.perf_counter() - t_start)

    def after_round(next_round: int) -> None:  # each time `every` more submaps are finished across the team
        nonlocal finished
        done = _finished_submaps(team)
        if every and done - finished >= every:
            finished = done
            checkpoint(next_round)

    try:
        with TeamRounds(team, enabled=progress, observer=observer) as show:
            if start:
                show(start, rounds, team.status(start, rounds, 0.0))
            wall = team.run(ds.agents, limits=caps, stride=stride, progress=show, strict=strict, start=start,
                            after_round=after_round)
        if every and start < rounds:  # every frame done: a kill in the refinement resumes at the refinement
            checkpoint(rounds)
    finally:
        for j in team.journals:
            j.close()
    wall = time.perf_counter() - t_start
    metrics = finish_team(team, ds, out, wall_s=wall, cpu0=cpu0, render_views=render_views, progress=progress,
                          observer=observer, run_info={"frame_stride": stride, "frame_caps": caps})
    (out / CHECKPOINT).unlink(missing_ok=True)  # a complete run needs none; the journals stay
    return metrics


def finish_team(team: Team, ds, out: Path, *, wall_s: float, cpu0: float, render_views: int, progress: bool,
                observer=None, run_info: dict | None = None) -> dict:
    """After the last frame: the final optimisation, the merged map's refinement (config map_refine) and every
    output (slam.run.team_results). wall_s: seconds so far (the refinement's are added); cpu0: process time at
    the start. Returns the metrics written."""
    from swarmsplat.slam.dense.mapping.refine import refines_poses
    from swarmsplat.slam.io.progress import reporting
    from .team_results import render_metrics, write_team_results

    cfg = team.cfg
    wall = wall_s
    t_fin = time.perf_counter()
    team.finish()
    wall += time.perf_counter() - t_fin
    before, refined = None, {}
    if cfg.map_refine.iterations_per_keyframe > 0 and cfg.map_refine.max_iterations > 0:
        t_ev = time.perf_counter()
        before = render_metrics(team, ds, render_views, novel=False)  # not counted in the run's wall time
        if progress:
            n = sum(len(a.keyframes) for a in team.agents)
            print(f"[team] refining the merged map over {n} keyframes (map_refine: "
                  f"{cfg.map_refine.iterations_per_keyframe} steps per keyframe, at most "
                  f"{cfg.map_refine.max_iterations} per component)", file=sys.stderr)
        moved = refines_poses(cfg.map_refine, [kf for a in team.agents for kf in a.keyframes])
        traj_before = [team.trajectory(a) for a in range(len(team.agents))] if moved else None
        t_ref = time.perf_counter()
        with reporting(progress):
            refined = team.refine_map()
        wall += time.perf_counter() - t_ref
        if observer is not None:
            observer(team, force=True)
        before["seconds"] = t_ref - t_ev
        before["trajectories"] = traj_before
    return write_team_results(team, ds, out, wall_s=wall, cpu_s=time.process_time() - cpu0,
                              render_views=render_views, progress=progress, before_refine=before,
                              refine=refined, run_info=run_info)
