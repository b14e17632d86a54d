"""All robots of a monocular dataset in one process, talking through the simulated network on a schedule.

`run_swarm(dataset, out, config, ...)` drives the ticks (each robot reads `frames_per_tick` frames per tick and
keeps every `stride`-th as a keyframe), then writes the outputs (`swarm_results.py`). Every setting comes from the
config tree's `swarm` section (slam.config.SwarmConfig). The place-recognition model and the pair registrar are
built once and shared, as the same pretrained model would be loaded on every robot; an untrained BoW/VLAD
vocabulary is fitted on a spread of keyframes of all robots (the stand-in for a pretrained one) and saved as
`vocabulary.npz` so that robot processes (`swarm_processes.py`) load the very same one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import output_dir
from swarmsplat.slam.config import SlamConfig, SwarmConfig, with_section
from swarmsplat.slam.run.guard import SkipLog, guarded, keep, read_frame

from swarmsplat.slam.flocc.swarm.ending import MissionEnd
from swarmsplat.slam.flocc.swarm.node import NodeConfig, RobotNode
from swarmsplat.slam.flocc.swarm.optimiser import SolveConfig
from swarmsplat.slam.flocc.swarm.rendezvous import Schedule
from swarmsplat.slam.flocc.swarm.transport import Faults, InProcessNetwork


@dataclass
class SwarmSetup:
    """What every robot of a run shares: the dataset, keyframe choice, schedule and models."""

    dataset: object  # slam.io.datasets MultiAgentDataset (mono)
    stride: int
    schedule: Schedule
    recognizer: object
    registrar: object
    node_config: NodeConfig
    strict: bool = False  # stop at an unreadable keyframe image (default: skip it with a warning)
    out: Path | None = None  # where an in-process run writes (its partial results too)
    config: SlamConfig | None = None  # the config tree of the run, written as config.yaml with the outputs


def swarm_config(config: SlamConfig | SwarmConfig | None = None, **options) -> SlamConfig:
    """The config tree of a swarm run: `config` (a whole tree, or only its swarm section; None: the defaults) with
    `options` (SwarmConfig's fields, e.g. stride=2, formulation="ss") overriding its swarm section (validated)."""
    return with_section(config, "swarm", options)


def node_config(sw: SwarmConfig) -> NodeConfig:
    """A robot's NodeConfig (and its SolveConfig) from the swarm section."""
    from swarmsplat.slam.flocc.swarm.distributed import check_solve_config

    solve = SolveConfig(formulation=sw.formulation, solver=sw.solver, uniform_noise=sw.uniform_noise,
                        odo_sigma_rot=sw.odo_sigma_rot, odo_sigma_trans=sw.odo_sigma_trans,
                        loop_sigma_rot=sw.loop_sigma_rot, loop_sigma_trans=sw.loop_sigma_trans)
    check_solve_config(solve)
    return NodeConfig(threshold=sw.threshold, r_thr=sw.r_thr, k=sw.k, neighbour_timeout=sw.neighbour_timeout,
                      resend=sw.resend, end_timeout=sw.end_timeout, solve=solve)


def prepare(dataset: str | Path, config: SlamConfig | SwarmConfig | None = None, *,
            vocabulary_out: str | Path | None = None, **options) -> SwarmSetup:
    """Load the dataset, build the models (fitting VLAD if needed) and the schedule (config.swarm.schedule,
    default `Schedule.default`). options: SwarmConfig fields overriding config.swarm (`swarm_config`); `schedule`
    may also be a Schedule object."""
    from swarmsplat.registration.pair import make_registrar
    from swarmsplat.registration.place_recognition import VOCABULARY_BACKENDS, make_recognizer
    from swarmsplat.slam.io.datasets import load_dataset

    schedule = options.pop("schedule", None)
    if schedule is not None and not isinstance(schedule, Schedule):
        options["schedule"] = str(schedule)
    cfg = swarm_config(config, **options)
    sw = cfg.swarm
    ds = load_dataset(dataset)
    if len(ds.agents) < 2:
        raise InputError(f"{dataset}: a swarm needs at least two agents, found {len(ds.agents)}")
    if len(ds.agents) > 26:
        raise InputError(f"{dataset}: at most 26 robots are supported, found {len(ds.agents)}")
    for s in ds.agents:
        if s.odometry is None:
            raise InputError(f"{dataset}: agent {s.name} has no odometry.txt (a monocular dataset is needed)")
    n_frames = max(len(s) for s in ds.agents)
    if not isinstance(schedule, Schedule):
        schedule = Schedule.load(sw.schedule) if sw.schedule else Schedule.default(len(ds.agents), n_frames)
    registrar = make_registrar(sw.backend, checkpoint=sw.checkpoint, device=sw.device)
    recognizer = make_recognizer(sw.place, checkpoint=sw.place_checkpoint, device=sw.device)
    if sw.place in VOCABULARY_BACKENDS and not recognizer.trained:
        every = [(s, f) for s in ds.agents for f in range(0, len(s), sw.stride)]
        pick = every[:: max(1, len(every) // 60)]
        frames = [read_frame(s, f, SkipLog(quiet=True), strict=sw.strict) for s, f in pick]  # the feeder warns
        recognizer.fit([f.color for f in frames if f is not None], seed=0)
        if vocabulary_out:
            recognizer.save(vocabulary_out)
    return SwarmSetup(ds, sw.stride, schedule, recognizer, registrar, node_config(sw), sw.strict, config=cfg)


class KeyframeFeeder:
    """Hands a node its keyframes as the frames it has read by each tick arrive. An unreadable keyframe image is
    skipped with a warning and logged in `skipped` (strict: raise)."""

    def __init__(self, seq, stride: int, strict: bool = False):
        self.seq, self.stride, self.next, self.strict = seq, stride, 0, strict
        self.skipped = SkipLog(seq.name)

    def feed(self, node: RobotNode, frames_read: int) -> int:
        n = 0
        while self.next < min(frames_read, len(self.seq)):
            if self.next % self.stride == 0:
                fr = read_frame(self.seq, self.next, self.skipped, strict=self.strict)
                if fr is not None and fr.T_world_cam_odom is not None:
                    node.add_keyframe(fr.color, fr.T_world_cam_odom, fr.timestamp)
                    n += 1
            self.next += 1
        return n


def make_nodes(setup: SwarmSetup, network: InProcessNetwork) -> tuple[list[RobotNode], list[KeyframeFeeder]]:
    nodes = [RobotNode(r, s.camera, network.endpoint(r), setup.recognizer, setup.registrar, setup.node_config)
             for r, s in enumerate(setup.dataset.agents)]
    return nodes, [KeyframeFeeder(s, setup.stride, setup.strict) for s in setup.dataset.agents]


def simulate(setup: SwarmSetup, *, faults: Faults | None = None, progress: bool = False, on_tick=None):
    """Run every tick of the schedule in-process, then the end protocol (`MissionEnd`) until every robot has
    stopped. `on_tick(tick, network, nodes, feeders)` runs before each tick (tests inject kills and link changes
    there). Returns (nodes, network, feeders, ends): `ends[r]` is robot r's end protocol."""
    from swarmsplat.slam.io.progress import bar

    robots = list(range(len(setup.dataset.agents)))
    net = InProcessNetwork(robots, setup.schedule, faults)
    nodes, feeders = make_nodes(setup, net)
    sched = setup.schedule
    ends = [MissionEnd.on_schedule(n, sched, robots) for n in nodes]
    stopped: set[int] = set()
    keep(lambda status, reason: write_partial_swarm(setup, nodes, feeders, ends, status=status, reason=reason))
    with bar(sched.ticks, "[swarm] ticks", unit="tick", enabled=progress) as b:
        for tick in range(sched.ticks + max(e.timeout_ticks for e in ends) + 1):
            if tick >= sched.ticks and set(robots) <= stopped | net.killed:
                break
            if on_tick is not None:
                on_tick(tick, net, nodes, feeders)
            net.advance(tick)
            for r in robots:
                if r in net.killed or r in stopped:
                    continue
                feeders[r].feed(nodes[r], sched.frames_at(tick))
                nodes[r].step(tick)
                if tick >= sched.ticks - 1 and ends[r].step(tick):
                    stopped.add(r)
            if tick < sched.ticks:
                b.update(1, f"{sum(len(n.timestamps) for n in nodes)} keyframes")
    return nodes, net, feeders, ends


def robot_results(nodes, ends=None) -> tuple[dict, dict]:
    """(robot id -> what outputs.write_outputs needs, the final graphs: those of the lowest-id robot that solved).
    ends: each robot's end protocol (its report goes with the robot's results)."""
    robots = {r: {"trajectory": n.trajectory(), "odometry": np.array(n.odometry), "timestamps": np.array(n.timestamps),
                  "bytes": n.tx.stats.to_dict(), "estimate": n.estimate, "n_solves": n.n_solves,
                  "end": ends[r].report() if ends else None}
              for r, n in enumerate(nodes)}
    if nodes and nodes[0].dist is not None:  # no gather: every robot's own graph, for the outputs' evaluation
        for r, n in enumerate(nodes):
            robots[r].update(loop_scales=n.dist.loop_scales(), steps=n.dist.steps)
        return robots, {n.id: n.submission() for n in nodes if len(n.odometry)}
    leader = min((n for n in nodes if n.last_solution is not None), key=lambda n: n.id, default=None)
    final = {int(r): leader.subs[int(r)] for r in leader.solved_basis} if leader else {}
    return robots, final


def write_partial_swarm(setup: SwarmSetup, nodes, feeders, ends=None, *, status: str, reason: str) -> Path | None:
    """A swarm run cut short: every robot's keyframe trajectory so far and the outputs of `write_outputs` without
    the re-solved alternatives, metrics.json with `status` and `reason`."""
    from swarmsplat.slam.run.swarm_results import write_outputs

    if setup.out is None:
        return None
    robots, final = robot_results(nodes, ends)
    write_outputs(setup.out, setup, robots, final, mode="in-process", status=status, reason=reason,
                  skipped=[row for f in feeders for row in f.skipped.rows])
    return setup.out


@guarded("swarm")
def run_swarm(dataset: str | Path, out: str | Path, config: SlamConfig | SwarmConfig | None = None, *,
              progress: bool = True, **options) -> dict:
    """Run the whole team in one process and write the outputs to `out` (see `swarm_results.write_outputs`;
    config.yaml holds the config tree used). config: the config tree or its swarm section; options: SwarmConfig
    fields overriding it (formulation="ss", stride=2, schedule=PATH or a Schedule, ...).
    Returns the metrics dictionary that is also written as `metrics.json`. An unreadable keyframe image is
    skipped with a warning (swarm.strict: the run stops); an interrupt or failure mid-run writes the outputs so far
    with "status" "interrupted" / "failed" (`write_partial_swarm`) and re-raises."""
    from swarmsplat.slam.run.swarm_results import write_outputs

    out = output_dir(out, "--out")
    setup = prepare(dataset, config, vocabulary_out=out / "vocabulary.npz", **options)
    setup.out = out
    nodes, net, feeders, ends = simulate(setup, progress=progress)
    robots, final = robot_results(nodes, ends)
    return write_outputs(out, setup, robots, final, mode="in-process",
                         skipped=[row for f in feeders for row in f.skipped.rows])
