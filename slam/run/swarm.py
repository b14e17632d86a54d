"""All robots of a monocular dataset in one process, talking through the simulated network on a schedule.

`run_swarm(dataset, out, ...)` drives the ticks (each robot reads `frames_per_tick` frames per tick and keeps
every `stride`-th as a keyframe), then writes the outputs (`outputs.py`). The place-recognition model and the
pair registrar are built once and shared, as the same pretrained model would be loaded on every robot; an
untrained BoW/VLAD vocabulary is fitted on a spread of keyframes of all robots (the stand-in for a pretrained one)
and saved as `vocabulary.npz` so that robot processes (`launch.py`) load the very same one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import output_dir
from swarmsplat.slam.run.guard import SkipLog, guarded, keep, read_frame

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


def prepare(dataset: str | Path, *, stride: int = 4, schedule: Schedule | str | Path | None = None,
            place: str = "bow", place_checkpoint: str | None = None, backend: str = "classical",
            checkpoint: str | None = None, formulation: str = "is", solver: str = "lm", uniform_noise: bool = False,
            vocabulary_out: str | Path | None = None, device: str = "cpu", r_thr: float | None = None,
            k: float | None = None, strict: bool = False) -> SwarmSetup:
    """Load the dataset, build the models (fitting VLAD if needed) and the schedule (default: `Schedule.default`)."""
    from swarmsplat.registration.pair import make_registrar
    from swarmsplat.registration.place_recognition import VOCABULARY_BACKENDS, make_recognizer
    from swarmsplat.slam.io.datasets import load_dataset

    if stride < 1:
        raise InputError(f"--stride must be >= 1, got {stride}")
    ds = load_dataset(dataset)
    if len(ds.agents) < 2:
        raise InputError(f"{dataset}: a swarm needs at least two agents, found {len(ds.agents)}")
    if len(ds.agents) > 26:
        raise InputError(f"{dataset}: at most 26 robots are supported, found {len(ds.agents)}")
    for s in ds.agents:
        if s.odometry is None:
            raise InputError(f"{dataset}: agent {s.name} has no odometry.txt (a monocular dataset is needed)")
    n_frames = max(len(s) for s in ds.agents)
    if schedule is None:
        schedule = Schedule.default(len(ds.agents), n_frames)
    elif not isinstance(schedule, Schedule):
        schedule = Schedule.load(schedule)
    registrar = make_registrar(backend, checkpoint=checkpoint, device=device)
    recognizer = make_recognizer(place, checkpoint=place_checkpoint, device=device)
    if place in VOCABULARY_BACKENDS and not recognizer.trained:
        every = [(s, f) for s in ds.agents for f in range(0, len(s), stride)]
        pick = every[:: max(1, len(every) // 60)]
        frames = [read_frame(s, f, SkipLog(quiet=True), strict=strict) for s, f in pick]  # the feeder warns
        recognizer.fit([f.color for f in frames if f is not None], seed=0)
        if vocabulary_out:
            recognizer.save(vocabulary_out)
    cfg = NodeConfig(r_thr=r_thr, k=k,
                     solve=SolveConfig(formulation=formulation, solver=solver, uniform_noise=uniform_noise))
    return SwarmSetup(ds, stride, schedule, recognizer, registrar, cfg, strict)


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
    """Run every tick of the schedule in-process. `on_tick(tick, network, nodes, feeders)` runs before each
    tick (tests inject kills and link changes there). Returns (nodes, network, feeders)."""
    from tqdm import tqdm

    robots = list(range(len(setup.dataset.agents)))
    net = InProcessNetwork(robots, setup.schedule, faults)
    nodes, feeders = make_nodes(setup, net)
    keep(lambda status, reason: write_partial_swarm(setup, nodes, feeders, status=status, reason=reason))
    for tick in tqdm(range(setup.schedule.ticks), desc="swarm", disable=not progress, leave=False):
        if on_tick is not None:
            on_tick(tick, net, nodes, feeders)
        net.advance(tick)
        for r in robots:
            if r in net.killed:
                continue
            feeders[r].feed(nodes[r], setup.schedule.frames_at(tick))
            nodes[r].step(tick)
    return nodes, net, feeders


def robot_results(nodes) -> tuple[dict, dict]:
    """(robot id -> what outputs.write_outputs needs, the final graphs: those of the lowest-id robot that solved)."""
    robots = {r: {"trajectory": n.trajectory(), "odometry": np.array(n.odometry), "timestamps": np.array(n.timestamps),
                  "bytes": n.tx.stats.to_dict(), "estimate": n.estimate, "n_solves": n.n_solves}
              for r, n in enumerate(nodes)}
    leader = min((n for n in nodes if n.last_solution is not None), key=lambda n: n.id, default=None)
    final = {int(r): leader.subs[int(r)] for r in leader.solved_basis} if leader else {}
    return robots, final


def write_partial_swarm(setup: SwarmSetup, nodes, feeders, *, status: str, reason: str) -> Path | None:
    """A swarm run cut short: every robot's keyframe trajectory so far and the outputs of `write_outputs` without
    the re-solved alternatives, metrics.json with `status` and `reason`."""
    from swarmsplat.slam.run.swarm_results import write_outputs

    if setup.out is None:
        return None
    robots, final = robot_results(nodes)
    write_outputs(setup.out, setup, robots, final, mode="in-process", status=status, reason=reason,
                  skipped=[row for f in feeders for row in f.skipped.rows])
    return setup.out


@guarded("swarm")
def run_swarm(dataset: str | Path, out: str | Path, *, formulation: str = "is", solver: str = "lm",
              schedule: str | Path | Schedule | None = None, stride: int = 4, place: str = "bow",
              place_checkpoint: str | None = None, backend: str = "classical", checkpoint: str | None = None,
              uniform_noise: bool = False, r_thr: float | None = None, k: float | None = None,
              progress: bool = True, strict: bool = False) -> dict:
    """Run the whole team in one process and write the outputs to `out` (see `outputs.write_outputs`).
    Returns the metrics dictionary that is also written as `metrics.json`. An unreadable keyframe image is
    skipped with a warning (strict: the run stops); an interrupt or failure mid-run writes the outputs so far
    with "status" "interrupted" / "failed" (`write_partial_swarm`) and re-raises."""
    from swarmsplat.slam.run.swarm_results import write_outputs

    out = output_dir(out, "--out")
    setup = prepare(dataset, stride=stride, schedule=schedule, place=place, place_checkpoint=place_checkpoint,
                    backend=backend, checkpoint=checkpoint, formulation=formulation, solver=solver,
                    uniform_noise=uniform_noise, vocabulary_out=out / "vocabulary.npz", r_thr=r_thr, k=k,
                    strict=strict)
    setup.out = out
    nodes, net, feeders = simulate(setup, progress=progress)
    robots, final = robot_results(nodes)
    return write_outputs(out, setup, robots, final, mode="in-process",
                         skipped=[row for f in feeders for row in f.skipped.rows])
