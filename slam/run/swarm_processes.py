"""One robot per process over Zenoh: `run_robot` is what `swarmsplat robot --id K` runs; `launch` starts N of them
on this machine, gives them a common tick 0 once every one is connected, and gathers their outputs.

Every robot reads the same config tree (`--config out/config.yaml`, written by `launch`). A robot process writes
`robots/<agent>/`: `state.npz` (keyframe trajectory, odometry, stamps), `bytes.json`, and
its held estimate and (if it ever optimised) the graphs of its last solve as swarm messages (`*.msg`, the same
safe encoding as on the wire). `launch` then writes the same outputs as an in-process run (`swarm_results.py`).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError, SwarmsplatError
from swarmsplat.kernels.fileio import atomic_path, atomic_write_bytes, atomic_write_text, output_dir
from swarmsplat.slam.config import SlamConfig, SwarmConfig
from swarmsplat.slam.run.guard import guarded, keep

from swarmsplat.slam.flocc.swarm import messages as M


@guarded("robot")
def run_robot(dataset: str | Path, robot: int, out: str | Path, config: SlamConfig | SwarmConfig | None = None, *,
              start_time: float | None = None, run: str = "swarmsplat", **options) -> Path:
    """Run robot `robot` of `dataset` on Zenoh until the schedule and then the end protocol (`MissionEnd`: every
    robot in range holds the final estimate, or swarm.end_timeout) are over; write its outputs under `out`.

    config: the config tree (or its swarm section) every robot of the run shares; options: SwarmConfig fields
    overriding its swarm section (port_base, stride, schedule, place, place_checkpoint, formulation, ...).
    start_time: epoch seconds of tick 0 (None: read it from stdin after printing `ready`, as `launch` does).
    The VLAD/BoW vocabulary must be given (swarm.place_checkpoint) so that every robot describes images alike.
    Interrupted (SIGINT / SIGTERM, e.g. from `launch`) or failing, it writes its state so far and re-raises.
    """
    from swarmsplat.slam.flocc.swarm.clocked import TickClock, run_clocked
    from swarmsplat.slam.flocc.swarm.ending import MissionEnd
    from swarmsplat.slam.flocc.swarm.node import RobotNode
    from swarmsplat.slam.flocc.swarm.optimiser import warm_up
    from swarmsplat.slam.run.swarm import KeyframeFeeder, prepare, swarm_config
    from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport

    cfg = swarm_config(config, **options)
    sw = cfg.swarm
    if robot < 0:
        raise InputError(f"--id must be >= 0, got {robot}")
    check_port_base(sw.port_base, robot + 1)
    output_dir(out, "--out")
    if sw.place in ("bow", "vlad") and not sw.place_checkpoint:
        raise InputError("a robot process needs the shared vocabulary: --place-checkpoint VOCAB.npz")
    setup = prepare(dataset, cfg)
    n = len(setup.dataset.agents)
    if not 0 <= robot < n:
        raise InputError(f"--id {robot}: the dataset has robots 0..{n - 1}")
    check_port_base(sw.port_base, n)
    seq = setup.dataset.agents[robot]
    clock = TickClock()
    tx = ZenohTransport(robot, list(range(n)), run=run, port_base=sw.port_base, schedule=setup.schedule,
                        clock=clock)
    node = RobotNode(robot, seq.camera, tx, setup.recognizer, setup.registrar, setup.node_config)
    feeder = KeyframeFeeder(seq, setup.stride, setup.strict)
    warm_up()
    tx.wait_for_peers(60.0)
    d = Path(out) / "robots" / seq.name
    sched = setup.schedule
    end = MissionEnd.on_schedule(node, sched, range(n))
    keep(lambda status, reason: _write_state(d, robot, node, tx, feeder, None, end, status=status, reason=reason))
    if start_time is None:
        print("ready", flush=True)
        start_time = float(sys.stdin.readline())

    def step(tick: int) -> bool:
        feeder.feed(node, sched.frames_at(tick))
        node.step(tick)
        return tick >= sched.ticks - 1 and end.step(tick)

    try:  # the schedule, then the end protocol: at most end.timeout_ticks more ticks
        skipped = run_clocked(step, sched.ticks + end.timeout_ticks, start_time, sched.tick_seconds, clock)
    finally:
        tx.close()
    if end.status != "complete":
        print(f"robot {robot}: the end protocol timed out after {end.report()['ticks']} ticks; missing robots "
              f"{end.report()['missing']}", file=sys.stderr, flush=True)
    return _write_state(d, robot, node, tx, feeder, skipped, end)


def _write_state(d: Path, robot: int, node, tx, feeder, skipped_ticks: int | None, end=None, *,
                 status: str = "complete", reason: str | None = None) -> Path:
    """A robot process's outputs (the module docstring), each written atomically; bytes.json last, so a robot
    folder with bytes.json is whole."""
    d.mkdir(parents=True, exist_ok=True)
    with atomic_path(d / "state.npz") as tmp:
        np.savez(tmp, trajectory=node.trajectory(), odometry=np.array(node.odometry),
                 timestamps=np.array(node.timestamps))
    if node.estimate is not None:
        atomic_write_bytes(d / "estimate.msg", M.encode(node.estimate, robot, 0))
    if node.solved_basis:
        for r in node.solved_basis:
            atomic_write_bytes(d / f"graph_{int(r)}.msg", M.encode(node.subs[int(r)], int(r), 0))
    if node.dist is not None:  # the distributed solve: its own graph and loop scales, for the run's evaluation
        atomic_write_bytes(d / f"graph_{robot}.msg", M.encode(node.submission(), robot, 0))
        scales = node.dist.loop_scales()
        atomic_write_text(d / "distributed.json", json.dumps({"steps": node.dist.steps, "loop_scales": [
            [int(ki), int(kj), float(s)] for (ki, kj), s in sorted(scales.items())]}))
    atomic_write_text(d / "bytes.json", json.dumps({**tx.stats.to_dict(), "n_solves": node.n_solves,
                                                   "skipped_ticks": skipped_ticks, "status": status,
                                                   "reason": reason, "skipped_frames": feeder.skipped.rows,
                                                   "end": end.report() if end is not None else None}))
    return d


def check_port_base(port_base: int, robots: int) -> None:
    """Robot K listens on TCP port port_base + K: every one of them must be a valid port."""
    if not 1 <= port_base <= 65536 - max(robots, 1):
        raise InputError(f"--port-base {port_base}: robots listen on port-base + id, which must lie in 1..65535 "
                         f"for all {robots} robots")


@guarded("swarm")
def launch(dataset: str | Path, out: str | Path, config: SlamConfig | SwarmConfig | None = None, *,
           timeout: float | None = None, **options) -> dict:
    """Start one `swarmsplat robot` process per robot, wait for them, and write the run's outputs. config: the
    config tree (or its swarm section); options: SwarmConfig fields overriding it (port_base, stride, schedule,
    place, backend, formulation, solver, uniform_noise, ...). The robots read the tree from `out/config.yaml`,
    with the schedule (`out/schedule.yaml`) and the shared vocabulary filled in.
    An interrupt is passed on to the robots (SIGINT), which write their state; a robot process that dies leaves
    the others to finish without it (their end protocol reports it missing). The outputs are then gathered from
    the robots that wrote their state, with metrics.json "status" "interrupted" / "failed"."""
    from swarmsplat.slam.run.swarm import prepare, swarm_config

    cfg = swarm_config(config, **{k: v for k, v in options.items() if k != "schedule"})
    port_base = cfg.swarm.port_base
    check_port_base(port_base, 1)
    out = output_dir(out, "--out")
    vocab = cfg.swarm.place_checkpoint
    setup = prepare(dataset, cfg, vocabulary_out=None if vocab else out / "vocabulary.npz",
                    **{k: v for k, v in options.items() if k == "schedule"})
    if cfg.swarm.place in ("bow", "vlad") and not vocab:
        vocab = str(out / "vocabulary.npz")
    sched_path = out / "schedule.yaml"
    import yaml

    atomic_write_text(sched_path, yaml.safe_dump(setup.schedule.to_dict(), sort_keys=False))
    setup.config = setup.config.override({"swarm": {"schedule": str(sched_path), "place_checkpoint": vocab}})
    atomic_write_text(out / "config.yaml", setup.config.to_yaml())
    n = len(setup.dataset.agents)
    check_port_base(port_base, n)
    run_name = f"r{os.getpid()}"
    cmd = lambda r: [sys.executable, "-m", "swarmsplat.slam", "robot", "--id", str(r), str(dataset),  # noqa: E731
                     "--out", str(out), "--config", str(out / "config.yaml"), "--run", run_name]
    # Own sessions: a Ctrl-C in the terminal reaches this process only, which passes it on once (_stop); a second
    # signal would make a robot exit before its state is written.
    procs = [subprocess.Popen(cmd(r), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              start_new_session=True) for r in range(n)]

    def save(status: str, reason: str) -> Path:
        gather(out, setup, status=status, reason=reason)
        return out

    keep(save)
    try:
        for r, p in enumerate(procs):
            line = p.stdout.readline().strip()
            if line != "ready":
                raise SwarmsplatError(f"robot {r} did not start: {(line + p.stderr.read())[-800:]}")
        start = time.time() + 2.0
        for p in procs:
            p.stdin.write(f"{start}\n")
            p.stdin.flush()
        limit = timeout or setup.schedule.ticks * setup.schedule.tick_seconds * 3 + cfg.swarm.end_timeout + 120
        failed = []
        for r, p in enumerate(procs):  # a robot that dies does not stop the others: they finish without it
            _, err = p.communicate(timeout=limit)
            if p.returncode != 0:
                failed.append(f"robot {r} failed (exit {p.returncode}): {err[-800:]}")
        if failed:  # the outputs of the robots that finished are gathered (status "failed")
            raise SwarmsplatError("; ".join(failed))
    except BaseException:
        _stop(procs)
        raise
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    return gather(out, setup)


def _stop(procs, wait_s: float = 10.0) -> None:
    """Ask every running robot to stop (SIGINT: it writes its state) and wait up to `wait_s` for all of them."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    end = time.time() + wait_s
    for p in procs:
        try:
            p.wait(timeout=max(0.0, end - time.time()))
        except subprocess.TimeoutExpired:
            pass


def gather(out: Path, setup, *, status: str = "complete", reason: str | None = None) -> dict:
    """Read the robot processes' outputs and write the run's (`outputs.write_outputs`). A run cut short
    (status "interrupted" / "failed") gathers the robots that wrote their state and leaves out the others."""
    from swarmsplat.slam.run.swarm_results import write_outputs

    robots, final, skipped = {}, {}, []
    for r, seq in enumerate(setup.dataset.agents):
        d = out / "robots" / seq.name
        if status != "complete" and not (d / "bytes.json").is_file():
            continue
        st = np.load(d / "state.npz")
        b = json.loads((d / "bytes.json").read_text())
        skipped += b.pop("skipped_frames", [])
        b.pop("status", None), b.pop("reason", None)
        end = b.pop("end", None)
        est = M.decode((d / "estimate.msg").read_bytes())[1] if (d / "estimate.msg").exists() else None
        robots[r] = {"trajectory": st["trajectory"], "odometry": st["odometry"], "timestamps": st["timestamps"],
                     "bytes": b, "estimate": est, "n_solves": b.get("n_solves", 0), "end": end}
        graphs = sorted(d.glob("graph_*.msg"))
        if (d / "distributed.json").is_file():  # every robot solved its own part: its graph and loop scales
            dj = json.loads((d / "distributed.json").read_text())
            robots[r].update(steps=dj["steps"], loop_scales={(ki, kj): s for ki, kj, s in dj["loop_scales"]})
            final.update({int(g.stem.split("_")[1]): M.decode(g.read_bytes())[1] for g in graphs})
        elif graphs and not final:  # the lowest robot that optimised: its last solve is the team's
            final = {int(g.stem.split("_")[1]): M.decode(g.read_bytes())[1] for g in graphs}
    return write_outputs(out, setup, robots, final, mode="zenoh", status=status, reason=reason, skipped=skipped)


# ------------------------------------------------------------------------- the distributed pose-graph solver
def solve_graph_processes(inputs: list[str], workdir: str | Path, *, initial_poses: dict, settings, rounds: int,
                          information: str = "repair", port_base: int = 17600, run: str = "graph",
                          crash: dict[int, int] | None = None, timeout: float = 600.0) -> dict:
    """`swarmsplat graph solve --distributed --processes`: one process per robot of the team in `inputs`, each
    reading the files, holding its part (graph.distributed) and running slam.flocc.swarm.solver_node over Zenoh on
    localhost (robot K on port_base + K). `initial_poses`: the team's initial estimate (written to `workdir` for
    the robots). `crash`: robot number -> the round after which that robot's process dies without a word (fault
    tests). `rounds`: the rounds to run (with `settings.gnc_plan`, its total). Returns the robots' poses, scales and
    owned loops' GNC weights merged, their bytes and which robots finished."""
    import pickle

    from swarmsplat.graph.distributed.partition import partition
    from swarmsplat.graph.team_files import read_team

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    graph = read_team(inputs, information=information)
    robots = sorted(partition(graph))
    check_port_base(port_base, max(robots) - ord("a") + 1)
    keys = np.array(sorted(initial_poses), dtype=np.uint64)
    np.savez(workdir / "initial.npz", keys=keys, poses=np.stack([initial_poses[int(k)] for k in keys]))
    (workdir / "settings.pkl").write_bytes(pickle.dumps(settings))
    code = ("import json, sys; from swarmsplat.slam.run.swarm_processes import _solver_process; "
            "_solver_process(*json.loads(sys.argv[1]))")
    t0 = time.time()
    crash = crash or {}
    procs = {r: subprocess.Popen([sys.executable, "-c", code, json.dumps(
        [list(map(str, inputs)), information, r, robots, rounds, port_base, run, str(workdir),
         crash.get(r - ord("a"))])]) for r in robots}
    while any(p.poll() is None for p in procs.values()) and time.time() - t0 < timeout:
        time.sleep(0.05)
    for p in procs.values():
        if p.poll() is None:
            p.kill()
        p.wait()
    poses, scales, weights, bytes_total, finished = {}, {}, {}, 0, []
    for r in robots:
        f = workdir / f"robot_{r - ord('a')}.npz"
        if not f.is_file():
            continue
        z = np.load(f)
        poses.update({int(k): T for k, T in zip(z["keys"], z["poses"])})
        scales.update({int(n): float(s) for n, s in zip(z["scale_edges"], z["scales"])})
        weights.update({int(n): float(w) for n, w in zip(z["weight_edges"], z["weights"])})
        bytes_total += int(z["bytes_sent"])
        finished.append(r)
    return {"graph": graph, "poses": poses, "scales": scales, "weights": weights, "bytes_total": bytes_total,
            "robots": robots,
            "finished": finished, "time_s": time.time() - t0}


def _solver_process(inputs, information, robot, robots, rounds, port_base, run, workdir, crash_after=None) -> None:
    """A robot process of `solve_graph_processes`: its part, the Zenoh transport, the rounds, its estimate."""
    import pickle

    from swarmsplat.graph.distributed.partition import partition
    from swarmsplat.graph.distributed.robot import RobotSolver
    from swarmsplat.graph.team_files import read_team
    from swarmsplat.slam.flocc.swarm.solver_node import CODEC, run_solver_robot, transport_id
    from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport

    workdir = Path(workdir)
    graph = read_team(inputs, information=information)
    parts = partition(graph)
    settings = pickle.loads((workdir / "settings.pkl").read_bytes())
    z = np.load(workdir / "initial.npz")
    initial = {int(k): T for k, T in zip(z["keys"], z["poses"])}
    from swarmsplat.graph.distributed.team import shared_s0

    settings.shared_s0 = shared_s0(graph, settings)
    solver = RobotSolver(parts[robot], dict(enumerate(graph.edges)), initial, settings)
    transport = ZenohTransport(transport_id(robot), [transport_id(r) for r in robots], run=run, port_base=port_base,
                               codec=CODEC)
    try:
        transport.wait_for_peers(30.0)

        def crash(k):
            if k == crash_after:
                time.sleep(0.5)  # its last estimate leaves first
                os._exit(1)  # a robot that vanishes: no goodbye, no output

        info = run_solver_robot(solver, transport, {r: p.colour for r, p in parts.items()}, rounds, on_round=crash)
    finally:
        transport.close()
    keys = np.array(solver.part.keys, dtype=np.uint64)
    own = sorted(n for n in solver.part.owned if n in solver.scales)
    owned = sorted(solver.part.owned)
    with atomic_path(workdir / f"robot_{transport_id(robot)}.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, keys=keys, poses=np.stack([solver.poses[int(k)] for k in keys]),
                     scale_edges=np.array(own, dtype=np.int64), scales=np.array([solver.scales[n] for n in own]),
                     weight_edges=np.array(owned, dtype=np.int64),
                     weights=np.array([solver.weights.get(n, 1.0) for n in owned]),
                     bytes_sent=transport.stats.to_dict()["sent_total"], timeouts=info["timeouts"],
                     gone=np.array(info["gone"], dtype=np.int64))
