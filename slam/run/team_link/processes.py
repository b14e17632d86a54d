"""The GRAND-SLAM team across processes: `serve_team` is what `swarmsplat server` runs, `run_team_agent` what
`swarmsplat agent ... --server ENDPOINT` runs, and `run_team_processes` (`swarmsplat run ... --processes`) starts
one agent process per sequence on this machine and serves them from this one, writing the in-process team's
outputs plus the link's byte counts (metrics.json "link", report.md).

The link is Zenoh in peer mode (slam.flocc.swarm.zenoh_transport, with the team's own message family): the server
listens, agents connect (across machines: `--connect tcp/HOST:PORT`). Node 0 is the server, node k + 1 agent k.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError, SwarmsplatError
from swarmsplat.kernels.fileio import atomic_write_text, output_dir

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.team.held import held_bytes
from swarmsplat.slam.run.guard import guarded

from . import messages as L


def _transport(node: int, nodes: list[int], *, listen: list[str], connect: list[str], run: str):
    from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport

    return ZenohTransport(node, nodes, run=run, codec=L.LINK, listen=listen, connect=connect, block=True)


def agent_journal(out):
    """The pose journal of a team agent given an output folder (out/progress/poses.tum: every frame up to its last
    keyframe, fsync'd at each keyframe, as `swarmsplat run` keeps one); None without a folder."""
    if out is None:
        return None
    from swarmsplat.slam.run.checkpoint import PoseJournal

    return PoseJournal(output_dir(out, "--out") / "progress" / "poses.tum")


def check_member(index: int, connect, listen) -> list[str]:
    """A team agent's index and endpoints checked (InputError naming the flag); returns the endpoints to connect."""
    if not 0 <= index <= 25:
        raise InputError(f"--id: expected 0 to 25, got {index}")
    _check_endpoints("--server/--connect", list(connect or []))
    _check_endpoints("--listen", list(listen or []))
    return list(connect or [])


def _check_endpoints(flag: str, endpoints: list[str]) -> None:
    for e in endpoints:
        proto, _, addr = str(e).partition("/")
        if proto not in ("tcp", "udp", "quic", "tls", "ws") or ":" not in addr:
            raise InputError(f"{flag} {e}: expected a Zenoh endpoint such as tcp/192.168.1.10:7447")


def serve_team(agents: int, out: str | Path, config: SlamConfig | None = None, *, dataset=None,
               listen: list[str] | None = None, connect: list[str] | None = None, run: str = "team",
               progress: bool = True, timeout: float | None = None, ros_keys: str = "rmw",
               domain: int | None = None, map_period: float = 10.0) -> dict:
    """Serve `agents` team agents until each has finished or is lost; write the team's outputs to `out`.
    dataset: the agents' MultiAgentDataset (or a path), agent k its k-th sequence, for the evaluation
    (ATE, renders); without it only the estimates, map, loops and link figures are written. A server started on
    a folder holding `link/journal.bin` continues from it (slam.run.team_link.server_node). While it serves, the
    agents' corrected trajectories, the loops and the merged map (every `map_period` s) go to ROS 2 on the link's
    Zenoh session (slam.run.ros2.team_feed; `ros_keys` "rmw", "bridge" or "off", ROS domain `domain`)."""
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.runtime import use_kernels
    from swarmsplat.slam.run.team import Team, finish_team
    from .server_node import ServerNode

    cfg = config or SlamConfig()
    if not 1 <= agents <= 26:
        raise InputError(f"--agents: expected 1 to 26 agents, got {agents}")
    listen = list(listen or [])
    connect = list(connect or [])
    _check_endpoints("--listen", listen)
    _check_endpoints("--connect", connect)
    if not listen and not connect:
        listen = [f"tcp/0.0.0.0:{cfg.link.port_base}"]
    ds = _load(dataset) if dataset is not None else None
    if ds is not None and len(ds.agents) != agents:
        raise InputError(f"--dataset {ds.root}: {len(ds.agents)} sequences for --agents {agents}")
    use_kernels(cfg.kernels)
    out = output_dir(out, "--out")
    names = [s.name for s in ds.agents] if ds is not None else [f"agent_{k}" for k in range(agents)]
    cams = [s.camera for s in ds.agents] if ds is not None else [PinholeCamera(1, 1, 0, 0, 1, 1)] * agents
    team = Team(cams, names, cfg, agent_class=AgentMirror)
    atomic_write_text(out / "config.yaml", cfg.to_yaml())
    tx = _transport(L.SERVER, list(range(agents + 1)), listen=listen, connect=connect, run=run)
    cpu0, t0 = time.process_time(), time.perf_counter()
    ros: list = []
    try:
        node = ServerNode(team, tx, journal=out / "link" / "journal.bin")
        from .registry import Registry, serve_registry  # agents without --id ask for their index by name

        registry = Registry(agents, fixed=names if ds is not None else None,
                            taken={p.name: a for a, p in enumerate(node.peers) if p.joined})
        queryable = serve_registry(tx.session, run, registry)
        ros = _team_topics(node, tx.session, ros_keys, domain, map_period)
        if progress:
            print(f"[server] waiting for {agents} agents on {', '.join(listen + connect)}", file=sys.stderr)
        node.run(progress=progress, timeout=timeout)
        if node.feed is not None:
            node.feed.finish(node)
        if not any(p.joined for p in node.peers):
            raise SwarmsplatError(f"no agent joined within {cfg.link.agent_timeout_s:.0f} s (link.agent_timeout_s) "
                                  f"on {', '.join(listen + connect)}")
        wall = time.perf_counter() - t0
        lost = [p.name for p in node.peers if p.lost]
        run_info = {"processes": True, "lost_agents": lost}
        if ds is not None and not lost:
            metrics = finish_team(team, ds, out, wall_s=wall, cpu0=cpu0, render_views=cfg.team.render_views,
                                  progress=progress, run_info=run_info)
        else:
            metrics = _write_estimates(team, out, wall, cpu0, run_info)
        metrics["link"] = node.link_metrics()
        if ros:
            metrics["link"]["ros2"] = ros[0].stats()  # the ROS 2 messages the server sent, per topic
        _add_link(out, metrics)
        node.finished()
        queryable.undeclare()
    finally:
        for part in ros:
            part.close()
        tx.close()
    return metrics


def _team_topics(node, session, ros_keys: str, domain: int | None, map_period: float) -> list:
    """Hang a TeamFeed on the server node (nothing for ros_keys "off"); returns what to close at the end."""
    if ros_keys == "off":
        return []
    from swarmsplat.slam.io.ros2 import Ros2Node, TeamTopics
    from swarmsplat.slam.run.ros2.team_feed import TeamFeed

    if map_period < 0:
        raise InputError(f"--map-period must be >= 0, got {map_period}")
    ros_node = Ros2Node(session, "swarmsplat_team", domain=domain, form=ros_keys)
    topics = TeamTopics(ros_node)
    node.feed = TeamFeed(topics, map_period_s=map_period)
    return [topics, ros_node]


serve_command = guarded("server")(serve_team)  # `swarmsplat server`: interrupts and failures reported as a run's


def _load(dataset):
    from swarmsplat.slam.io.datasets import MultiAgentDataset, load_dataset

    return dataset if isinstance(dataset, MultiAgentDataset) else load_dataset(dataset)


def _write_estimates(team, out: Path, wall: float, cpu0: float, run_info: dict) -> dict:
    """Without the agents' ground truth (or with an agent lost): the estimates, merged map, graphs and loops."""
    from swarmsplat.graph.g2o import write_g2o
    from swarmsplat.slam.dense.loops.loop_log import summarise, write_loops_csv
    from swarmsplat.slam.dense.ply import save_ply
    from swarmsplat.slam.io.jsonio import write_json
    from swarmsplat.slam.io.trajectory import write_tum

    team.finish()
    if not run_info.get("lost_agents"):
        team.refine_map()
    srv = team.server
    agents = []
    for a, ag in enumerate(team.agents):
        stamps, T = team.trajectory(a)
        if len(stamps):
            write_tum(out / "trajectories" / f"{ag.name}.txt", stamps, T)
            write_tum(out / "trajectories_no_lc" / f"{ag.name}.txt", *team.trajectory_no_lc(a))
        agents.append({"name": ag.name, "frames_tracked": len(ag.poses), "keyframes": len(ag.keyframes),
                       "submaps": len(ag.gmap.submaps), "gaussians": len(ag.gmap),
                       "component": team.agents[srv.slots[a].component].name,
                       "skipped_frames": ag.skipped_frames(),
                       "time_s": {"tracking": ag.time.tracking, "mapping": ag.time.mapping}})
    g, _ = srv.build_graph()
    if g.poses:
        write_g2o(g, out / "pose_graph_optimized.g2o", srv.last_graph[1] if srv.last_graph else g.poses)
    for root in srv.components():
        params = srv.display_map(root)
        if len(params):
            save_ply(out / ("map.ply" if root == 0 else f"map_{team.agents[root].name}.ply"), params,
                     max_color=None)
    write_loops_csv(out / "loops.csv", srv.records)
    summary = summarise(srv.records)
    metrics = {"status": "complete", "agents": agents, "loops": summary,
               "loops_accepted": summary["intra"]["accepted"] + summary["inter"]["accepted"],
               "loop_candidates": len(srv.records), "pose_graph_optimisations": srv.optimisations,
               "all_agents_joined": all(s.component == 0 for s in srv.slots),
               "time_s": {"wall": wall, "cpu": time.process_time() - cpu0, "server": dict(srv.time)},
               "run": run_info}
    write_json(out / "metrics.json", metrics)
    return metrics


def _add_link(out: Path, metrics: dict) -> None:
    """metrics.json gets "link"; report.md a section with the bytes per agent."""
    from swarmsplat.slam.io.jsonio import write_json

    write_json(out / "metrics.json", metrics)
    link = metrics["link"]
    rows = ["", "## Link (agents and server in separate processes)", "",
            f"Gaussians sent as {link['gaussians']}; \"of raw\": all bytes both ways against the agent's keyframes "
            "sent raw (8-bit RGB + 16-bit depth at its input frames' size"
            + (f": {link['raw_keyframe_bytes'] / 1e6:.3f} MB a keyframe)." if link["raw_keyframe_bytes"] else ")."),
            "",
            "| agent | keyframes | bytes from agent | bytes to agent | per keyframe | per submap | of raw |",
            "|---|---|---|---|---|---|---|"]
    for name, s in link["agents"].items():
        per_kf = f"{s['bytes_per_keyframe'] / 1e3:.1f} kB" if s["bytes_per_keyframe"] else "-"
        per_sm = f"{s['bytes_per_submap'] / 1e3:.1f} kB" if s["bytes_per_submap"] else "-"
        frac = f"{100 * s['fraction_of_raw']:.1f} %" if s["fraction_of_raw"] else "-"
        rows.append(f"| {name}{' (lost)' if s['lost'] else ''} | {s['keyframes']} | "
                    f"{sum(s['bytes_from_agent'].values()) / 1e6:.2f} MB | {sum(s['bytes_to_agent'].values()) / 1e3:.1f} kB"
                    f" | {per_kf} | {per_sm} | {frac} |")
    report = out / "report.md"
    text = report.read_text() if report.is_file() else "# Team run\n"
    atomic_write_text(report, text.rstrip("\n") + "\n" + "\n".join(rows) + "\n")


@guarded("agent")
def run_team_agent(seq, index: int, config: SlamConfig | None = None, *, name: str | None = None,
                   connect: list[str] | None = None, listen: list[str] | None = None, run: str = "team",
                   frames: int | None = None, stride: int | None = None, progress: bool = True,
                   strict: bool = False, out: str | Path | None = None, resume: bool = False) -> dict:
    """Agent `index` of a team (node index + 1) on sequence `seq`, sending to the server at `connect`: join, track
    and map every stride-th frame, send keyframes / submaps / poses, then wait for the server to acknowledge
    everything (link.finish_timeout_s). out: also write this agent's pose journal as it goes (progress/poses.tum),
    its checkpoints (progress/checkpoint.pkl, config checkpoint) and its own view (trajectory as corrected,
    link.json); resume: continue the agent killed in `out` from its last checkpoint (slam.run.team_link.member).
    Returns the agent's link figures."""
    from swarmsplat.slam.run.runtime import use_kernels
    from .member import MemberCheckpoints, member_identity

    cfg = config or SlamConfig()
    connect = check_member(index, connect, listen)
    stride = cfg.team.stride if stride is None else stride
    cap = frames if frames is not None else cfg.max_frames
    n = len(seq) if not cap else min(len(seq), int(cap))
    rounds = -(-n // stride)
    if resume and out is None:
        raise InputError("--resume continues the agent whose checkpoint is in --out: give --out")
    use_kernels(cfg.kernels)
    ckpt = MemberCheckpoints(output_dir(out, "--out"), member_identity(seq, cfg, n, index, stride), cfg) \
        if out is not None else None
    try:
        resumed = ckpt.open(resume) if ckpt is not None else None
        return _member_rounds(seq, index, cfg, ckpt, resumed, name=name or seq.name, connect=connect, listen=listen,
                              run=run, rounds=rounds, stride=stride, progress=progress, strict=strict, out=out)
    finally:
        if ckpt is not None:
            ckpt.close()


def _member_rounds(seq, index: int, cfg: SlamConfig, ckpt, resumed, *, name: str, connect, listen, run: str,
                   rounds: int, stride: int, progress: bool, strict: bool, out) -> dict:
    """run_team_agent's work once its folder is taken: join, the rounds, the end."""
    from .agent_node import AgentNode

    tx = _transport(index + 1, [L.SERVER, index + 1], listen=list(listen or []), connect=connect, run=run)
    say = (lambda *a, **k: print(*a, **k)) if progress else (lambda *a, **k: None)
    try:
        make = lambda: AgentNode(seq.camera, cfg, name, tx)  # noqa: E731
        node, start = ckpt.start(resumed, make, tx, say=lambda t: say(t, file=sys.stderr)) if ckpt else (make(), 0)
        node.parent = _parent()
        node.join(rounds, cfg.link.connect_timeout_s, say=say)
        t0, last = time.monotonic(), time.monotonic()
        for i in range(start, rounds):
            n_sm = len(node.agent.gmap.submaps)
            node.step_round(seq, i, stride, strict)
            if ckpt is not None:
                ckpt.after_round(node, i, n_sm)
            if progress and time.monotonic() - last > 10:
                last = time.monotonic()
                say(f"[{name}] round {i + 1}/{rounds}  keyframes {len(node.agent.keyframes)}  "
                    f"queued {len(node.outbox.items)}  {time.monotonic() - t0:.0f}s  "
                    f"held {held_bytes(node.agent, node.outbox) / 2**20:.0f} MB", file=sys.stderr)
        if ckpt is not None and start < rounds:  # every round done: a kill while waiting for the server resumes here
            ckpt.save(node, rounds)
        figures = finish_agent(node, rounds, tx, name, out, say)
        if ckpt is not None and figures["acknowledged"]:
            ckpt.done()
    finally:
        tx.close()
    return figures


PARENT_ENV = "SWARMSPLAT_TEAM_PARENT"  # set by run_team_processes: its agents stop when it is gone


def _parent() -> int | None:
    """The pid of the `run --processes` that started this agent process (None: started on its own)."""
    v = os.environ.get(PARENT_ENV, "")
    return int(v) if v.isdigit() else None


def finish_agent(node, rounds: int, tx, name: str, out, say) -> dict:
    """A team agent's end: its last messages, acknowledged within link.finish_timeout_s; its link figures (written
    with its trajectory as corrected to `out`/link.json and trajectory.txt when `out` is given)."""
    import json

    cfg = node.cfg
    acked = node.finish(rounds, cfg.link.finish_timeout_s)
    if node.journal is not None:
        node.journal.close()
    if not acked:
        say(f"[{name}] the server did not acknowledge {len(node.outbox.items)} messages within "
            f"{cfg.link.finish_timeout_s:.0f} s (link.finish_timeout_s)", file=sys.stderr)
    figures = {"name": name, "acknowledged": acked, **node.outbox.stats(), "bytes": tx.stats.to_dict(),
               "corrections": node.corrections}
    if out is not None:
        from swarmsplat.slam.io.trajectory import write_tum

        d = output_dir(out, "--out")
        stamps, T = node.agent.trajectory()
        if len(stamps):
            write_tum(d / "trajectory.txt", stamps, T)
        atomic_write_text(d / "link.json", json.dumps(figures, indent=1))
    return figures


@guarded("team")
def run_team_processes(dataset: str | Path, out: str | Path, config: SlamConfig | None = None, *,
                       frames: int | None = None, split: str | None = None, loaded=None, progress: bool = True,
                       timeout: float | None = None, resume: bool = False) -> dict:
    """`swarmsplat run DATASET --processes`: one `swarmsplat agent --server` process per sequence of `dataset` (a
    multi-agent dataset, or one sequence cut by `split` ranges), served by this process on localhost. Writes the
    in-process team's outputs, plus metrics.json "link"; each agent keeps its checkpoints in link/<agent>/.
    loaded: the dataset as already loaded (and split). resume: continue the killed run in `out`: the server
    replays its journal (link/journal.bin), each agent resumes from its checkpoint, an agent the server had
    acknowledged entirely is not started again."""
    from swarmsplat.slam.run.checkpoint import CHECKPOINT, has_checkpoint, team_identity
    from .member import agent_folder, forget_member, member_complete, team_resume

    cfg = config or SlamConfig()
    if loaded is not None:
        ds = loaded
    elif split:
        from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence

        ds = split_sequence(_load(dataset).agents[0], parse_ranges(split))
    else:
        ds = _load(dataset)
    if len(ds.agents) < 2:
        raise InputError(f"--processes runs a team, but {dataset} holds one sequence (cut it with --split)")
    out = output_dir(out, "--out")
    caps = [len(s) if not (frames or cfg.max_frames) else min(len(s), int(frames or cfg.max_frames))
            for s in ds.agents]
    team_resume(out, team_identity(ds, cfg, caps, cfg.team.stride), resume=resume)
    if not resume:
        (out / "link" / "journal.bin").unlink(missing_ok=True)  # a new run: an earlier run's journal is not replayed
    cfg_path = out / "link" / "config.yaml"
    atomic_write_text(cfg_path, cfg.to_yaml())
    port = _free_port(cfg.link.port_base)
    endpoint = f"tcp/127.0.0.1:{port}"
    run = f"t{os.getpid()}"
    folders = [agent_folder(out, s.name) for s in ds.agents]
    if not resume:  # a new run: what an earlier run's agents left is not resumed
        for d in folders:
            forget_member(d)
    again = [resume and (has_checkpoint(d) or (d / "config.yaml").is_file()) for d in folders]
    cmd = lambda k, s: [sys.executable, "-m", "swarmsplat.slam", "agent", str(dataset), "--name", s.name,  # noqa: E731
                        "--server", endpoint, "--id", str(k), "--config", str(cfg_path), "--run", run, "--quiet",
                        "--out", str(folders[k]), *(["--resume"] if again[k] else []),
                        *(["--split", split] if split else []), *(["--frames", str(frames)] if frames else [])]
    # an agent whose messages the server acknowledged entirely (its journal has them) is not started again
    start = [k for k in range(len(ds.agents)) if not (resume and member_complete(folders[k]))]
    for k in set(range(len(ds.agents))) - set(start):  # killed between its end and removing its checkpoint
        (folders[k] / CHECKPOINT).unlink(missing_ok=True)
    logs = {k: open(out / "link" / f"{ds.agents[k].name}.log", "a" if resume else "w") for k in start}
    env = {**os.environ, PARENT_ENV: str(os.getpid())}
    procs = {k: subprocess.Popen(cmd(k, ds.agents[k]), stdout=logs[k], stderr=subprocess.STDOUT,
                                 start_new_session=True, env=env) for k in start}
    try:
        m = serve_team(len(ds.agents), out, cfg, dataset=ds, listen=[endpoint], run=run, progress=progress,
                       timeout=timeout)
        for p in procs.values():
            try:
                p.wait(timeout=max(30.0, cfg.link.finish_timeout_s))
            except subprocess.TimeoutExpired:
                pass
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
        for f in logs.values():
            f.close()
    failed = [f"{ds.agents[k].name} (exit {p.returncode}, see link/{ds.agents[k].name}.log)"
              for k, p in procs.items() if p.returncode not in (0, None)]
    if failed:
        raise SwarmsplatError("agent processes failed: " + ", ".join(failed))
    return m


def _free_port(start: int) -> int:
    import socket

    for port in range(start, start + 200):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise SwarmsplatError(f"no free TCP port in {start}..{start + 199} (link.port_base)")
