"""Every process of a team over Zenoh resumes. An agent process (`swarmsplat agent DATA --server ... --out DIR`)
killed with SIGKILL mid-run and started again with `--resume` continues from its checkpoint, and its server takes it
back without a duplicated keyframe, frame or loop; a whole `swarmsplat run --processes` killed mid-run continues
with `--resume` from the server's journal and each agent's checkpoint. Both end with the uninterrupted team's
outputs, byte for byte: a lossless link gives the in-process team's outputs (tests/test_team_link.py) and a
resumed agent recomputes the rounds after its checkpoint bit for bit (tests/test_run_checkpoint.py); the cloud
routes are off, as KISS-Matcher's parallel matching is not bit-reproducible across processes. A generated sequence cut into two overlapping agents that join. Skipped without eclipse-zenoh."""

from __future__ import annotations

import csv
import json
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.flocc.swarm.zenoh_transport import zenoh_available

pytestmark = pytest.mark.skipif(not zenoh_available(), reason="eclipse-zenoh is not installed")

REPO = Path(__file__).resolve().parents[1]
FRAMES, SPLIT = 24, "0:14,10:24"
CONFIG = {  # the team's logic, not the map's quality: tiny mapping, a submap (so a checkpoint) every 2 keyframes
    "mapping": {"iterations": 8, "first_iterations": 25},
    "tracking": {"refine": False},
    "keyframes": {"every": 2},
    "submaps": {"max_keyframes": 2},
    "loop_closure": {"min_index_gap": 2, "cloud_route": False},
    "server": {"tau_sim": 0.5, "cloud_route": False},
    "team": {"render_views": 2},
    "map_refine": {"iterations_per_keyframe": 0},
    "link": {"resend_s": 1.0, "agent_timeout_s": 60.0, "finish_timeout_s": 60.0, "images": "lossless",
             "gaussians": "float32", "cull_gaussians": False},
}
SAME = ["loops.csv", "map.ply", "pose_graph_optimized.g2o", "trajectories/agent_0.txt", "trajectories/agent_1.txt",
        "trajectories_no_lc/agent_0.txt", "trajectories_no_lc/agent_1.txt"]
BASE = [sys.executable, "-m", "swarmsplat.slam"]


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    """(folder, the generated sequence, the config file, the uninterrupted team's outputs and metrics)."""
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("agent_resume")
    data = generate(root / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=FRAMES))
    (root / "cfg.yaml").write_text(SlamConfig().override(CONFIG).to_yaml())
    _swarmsplat(["run", str(data), "--split", SPLIT, "--config", str(root / "cfg.yaml"), "--out",
                 str(root / "whole"), "--quiet"])
    m = json.loads((root / "whole" / "metrics.json").read_text())
    assert m["all_agents_joined"] and m["loops_accepted"] >= 1, "the split must join (corrections are sent)"
    return root, data, root / "cfg.yaml", root / "whole", m


def _swarmsplat(args: list[str]) -> subprocess.CompletedProcess:
    out = subprocess.run(BASE + args, capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _frames(journal: Path) -> int:
    """Frames in a pose journal (progress/poses.tum)."""
    try:
        return sum(1 for ln in journal.read_text().splitlines() if ln and not ln.startswith("#"))
    except OSError:
        return 0


def _checkpoint_header(path: Path) -> dict | None:
    try:
        with open(path, "rb") as f:
            return pickle.load(f)
    except (OSError, EOFError, pickle.UnpicklingError):
        return None


class _JournalWatch:
    """The keyframe ids of agent `agent` whose KeyframeMeta the server has journaled (link/journal.bin), read as
    the file grows (only the new records, only KeyframeMeta decoded)."""

    def __init__(self, journal: Path, agent: int):
        self.path, self.agent, self.off, self.ids = journal, agent, 0, set()

    def newest(self) -> int:
        from swarmsplat.slam.run.team_link import messages as L

        if self.path.is_file():
            with open(self.path, "rb") as f:
                f.seek(self.off)
                data = f.read()
            off = 0
            while off + 4 <= len(data):
                size = int.from_bytes(data[off:off + 4], "little")
                if off + 4 + size > len(data):
                    break
                record = data[off + 4: off + 4 + size]
                h = L.LINK.peek_header(record)
                if h.sender == self.agent + 1 and h.type_id == L.KeyframeMeta.TYPE:
                    self.ids.add(L.LINK.decode(record)[1].id)
                off += 4 + size
            self.off += off
        return max(self.ids, default=-1)


def _assert_whole_result(out: Path, whole: Path, m_whole: dict) -> dict:
    """The team's result in `out` is the uninterrupted one's: the same files byte for byte, every keyframe, frame
    and loop candidate once."""
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and m["all_agents_joined"]
    for a, b in zip(m["agents"], m_whole["agents"]):
        for k in ("keyframes", "submaps", "frames_tracked", "gaussians", "ate_rmse"):
            assert a[k] == b[k], (a["name"], k, a[k], b[k])
    rows = list(csv.reader((out / "loops.csv").open()))
    assert len(rows) == len(set(map(tuple, rows))), "a loop candidate twice"
    assert m["loop_candidates"] == m_whole["loop_candidates"] and m["loops_accepted"] == m_whole["loops_accepted"]
    for name in ("agent_0", "agent_1"):
        stamps = [ln.split()[0] for ln in (out / "trajectories" / f"{name}.txt").read_text().splitlines()
                  if not ln.startswith("#")]
        assert len(stamps) == len(set(stamps)), f"{name}: a frame twice"
    differ = [f for f in SAME if (out / f).read_bytes() != (whole / f).read_bytes()]
    assert not differ, f"{differ} differ from the uninterrupted team's"
    assert m["ate_rmse_team"] <= 1.1 * m_whole["ate_rmse_team"]  # implied by the above; the stated bound
    return m


def test_an_agent_killed_mid_run_resumes_and_the_server_takes_it_back(team, tmp_path):
    """SIGKILL of agent 1 once the server holds a keyframe it made after its last checkpoint; `--resume` makes
    that keyframe again, which the server keeps once."""
    root, data, cfg, whole, m_whole = team
    endpoint, run, out = f"tcp/127.0.0.1:{_free_port()}", f"r{os.getpid()}", tmp_path / "team"
    server = BASE + ["server", "--agents", "2", "--out", str(out), "--config", str(cfg), "--dataset", str(data),
                     "--split", SPLIT, "--listen", endpoint, "--run", run, "--quiet", "--ros-keys", "off"]
    agent = lambda k: BASE + ["agent", str(data), "--split", SPLIT, "--id", str(k), "--name", f"agent_{k}",  # noqa: E731
                              "--server", endpoint, "--config", str(cfg), "--run", run, "--quiet", "--out",
                              str(tmp_path / f"agent_{k}")]
    ckpt = tmp_path / "agent_1" / "progress" / "checkpoint.pkl"
    srv = subprocess.Popen(server, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    procs = [subprocess.Popen(agent(k), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
             for k in (0, 1)]
    watch = _JournalWatch(out / "link" / "journal.bin", 1)
    poses = tmp_path / "agent_1" / "progress" / "poses.tum"
    try:
        t_end = time.time() + 60
        while True:  # agent 1 journaled a keyframe after its last checkpoint: stop it there (SIGSTOP)
            assert time.time() < t_end and procs[1].poll() is None, "agent 1 ended before it could be killed"
            header = _checkpoint_header(ckpt)
            if header and _frames(poses) > header["journal"][1]:
                time.sleep(0.3)  # the keyframe's messages go out
                procs[1].send_signal(signal.SIGSTOP)
                header = _checkpoint_header(ckpt)  # that round may have written a checkpoint after its journal
                if _frames(poses) > header["journal"][1]:
                    break
                procs[1].send_signal(signal.SIGCONT)
            time.sleep(0.02)
        t_end, t_cont = time.time() + 60, time.time() + 5
        while watch.newest() < header["keyframes"]:  # the server has it: the resumed agent will send it again
            assert time.time() < t_end, "the server never received the keyframe made after the checkpoint"
            if time.time() > t_cont:  # its messages had not gone out: a moment more (a new submap takes rounds)
                procs[1].send_signal(signal.SIGCONT)
                time.sleep(0.1)
                procs[1].send_signal(signal.SIGSTOP)
                t_cont = time.time() + 5
            time.sleep(0.05)
        procs[1].send_signal(signal.SIGKILL)
        assert procs[1].wait(10) == -signal.SIGKILL
        assert _checkpoint_header(ckpt) == header and 0 < header["next_frame"] < 14, "killed mid-run"
        procs[1] = subprocess.Popen(agent(1) + ["--resume"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True, cwd=REPO)
        _, err = srv.communicate(timeout=120)
        assert srv.returncode == 0, err[-3000:]
        for p in procs:
            _, err = p.communicate(timeout=60)
            assert p.returncode == 0, err[-3000:]
    finally:
        for p in [srv, *procs]:
            if p.poll() is None:
                p.kill()
    m = _assert_whole_result(out, whole, m_whole)
    s = m["link"]["agents"]["agent_1"]
    assert s["keyframes"] == m_whole["agents"][1]["keyframes"]
    assert s["repeats_received"] > 0  # the keyframe made after the checkpoint, made and sent again
    assert not ckpt.exists() and json.loads((tmp_path / "agent_1" / "link.json").read_text())["acknowledged"]
    # the agent's own journal: every frame up to its last keyframe once, in order, as the uninterrupted team's
    stamps = lambda path: [ln.split()[0] for ln in path.read_text().splitlines() if not ln.startswith("#")]  # noqa: E731
    assert stamps(tmp_path / "agent_1" / "progress" / "poses.tum") == stamps(whole / "progress" / "agent_1.tum")


def test_a_killed_run_with_processes_resumes(team, tmp_path):
    """SIGKILL of `run --processes` (the server) once an agent has a checkpoint: its agents notice and stop;
    `run --processes --resume` replays the server's journal and resumes each agent from its checkpoint."""
    root, data, cfg, whole, m_whole = team
    out = tmp_path / "run"
    args = ["run", str(data), "--split", SPLIT, "--config", str(cfg), "--out", str(out), "--processes", "--quiet"]
    proc = subprocess.Popen(BASE + args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
    folders = [out / "link" / f"agent_{k}" for k in (0, 1)]
    ckpts = [d / "progress" / "checkpoint.pkl" for d in folders]
    done = lambda d: (d / "link.json").is_file()  # noqa: E731 - the agent ended, everything acknowledged
    try:
        t_end = time.time() + 60
        # each agent mid-run (a checkpoint) or done (one may finish before the other has started)
        while not (all(c.is_file() or done(d) for c, d in zip(ckpts, folders)) and any(c.is_file() for c in ckpts)):
            assert time.time() < t_end and proc.poll() is None, "the run ended before it could be killed"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
    assert (out / "link" / "journal.bin").stat().st_size > 0 and not (out / "metrics.json").exists()
    t_end = time.time() + 30
    while _processes_in(out):  # the killed run's agents see it gone and stop
        assert time.time() < t_end, "the agents of the killed run are still running"
        time.sleep(0.1)
    resumed = [k for k in (0, 1) if ckpts[k].is_file() and not done(folders[k])]
    assert resumed and all(0 < _checkpoint_header(ckpts[k])["next_frame"] <= 14 for k in resumed)
    _swarmsplat(args + ["--resume"])
    m = _assert_whole_result(out, whole, m_whole)
    assert m["link"]["replayed_messages"] > 0
    assert not any(c.exists() for c in ckpts)
    for k in (0, 1):  # an agent with a checkpoint was started again once, with --resume; a done one was not
        epoch = folders[k] / "progress" / "link_epoch"
        assert (epoch.read_text() == "1\n") if k in resumed else not epoch.exists(), k


def _processes_in(folder: Path) -> list[int]:
    """Processes whose command line names `folder` (Linux /proc)."""
    pids = []
    for p in Path("/proc").iterdir():
        try:
            if p.name.isdigit() and str(folder).encode() in (p / "cmdline").read_bytes():
                pids.append(int(p.name))
        except OSError:
            pass
    return pids


def test_resume_without_a_checkpoint_of_this_agent_is_one_line(team, tmp_path, capsys):
    from swarmsplat.slam.cli import main

    root, data, cfg, whole, m_whole = team
    member = lambda k, config=cfg: ["agent", str(data), "--split", SPLIT, "--id", str(k), "--name",  # noqa: E731
                                    f"agent_{k}", "--server", "tcp/127.0.0.1:9", "--config", str(config), "--quiet",
                                    "--resume"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(member(1) + ["--out", str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{empty} holds no run to resume" in err[0], err
    assert main(member(1)) == 2
    assert "give --out" in capsys.readouterr().err

    # another agent's checkpoint, and another config's
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence
    from swarmsplat.slam.run.checkpoint import save_checkpoint
    from swarmsplat.slam.run.team_link.agent_node import AgentNode
    from swarmsplat.slam.run.team_link.member import member_identity

    ds = split_sequence(load_dataset(data).agents[0], parse_ranges(SPLIT))
    c = SlamConfig.from_yaml(cfg)
    node = AgentNode(ds.agents[0].camera, c, "agent_0", tx=None)
    save_checkpoint(empty, member_identity(ds.agents[0], c, 14, 0, 1), node, next_frame=2, journal=(0, 0), wall_s=0)
    assert main(member(1) + ["--out", str(empty)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{empty} is a checkpoint of another run: sequence: 'agent_0' in the checkpoint, " \
                             f"'agent_1' now" in err[0], err
    other = tmp_path / "other.yaml"
    other.write_text(SlamConfig().override(CONFIG).override({"mapping": {"iterations": 9}}).to_yaml())
    assert main(member(0, other) + ["--out", str(empty)]) == 2
    assert "config.mapping.iterations: 8 in the checkpoint, 9 now" in capsys.readouterr().err

    # run --processes --resume: no run of agent processes there, or one of another config
    run = ["run", str(data), "--split", SPLIT, "--processes", "--quiet", "--resume", "--out"]
    assert main(run + [str(empty), "--config", str(cfg)]) == 2
    assert "holds no run of agent processes to resume" in capsys.readouterr().err
    (empty / "link").mkdir()
    from swarmsplat.slam.run.checkpoint import team_identity

    (empty / "link" / "identity.json").write_text(json.dumps(team_identity(ds, c, [14, 14], 1)))
    assert main(run + [str(empty), "--config", str(other)]) == 2
    err = capsys.readouterr().err
    assert "is a run of another dataset or config" in err and "config.mapping.iterations: 8" in err, err


class _Wire:
    """A transport that keeps what is sent and delivers nothing."""

    def __init__(self):
        self.sent = []

    def send(self, dest, msg):
        self.sent.append(msg)

    def poll(self):
        return []


def test_a_resumed_agent_numbers_its_messages_past_the_killed_ones_and_the_server_keeps_one_copy(tmp_path):
    """Over no network: the checkpoint keeps the queue (resent at once after the resume) but not the transport;
    each restart numbers new messages in a range of its own, so a message the killed process sent after the
    checkpoint never hides a new one with another content; the server keeps a keyframe and a frame made twice
    once."""
    import numpy as np

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.run.team_link import messages as L
    from swarmsplat.slam.run.team_link.agent_node import AgentNode
    from swarmsplat.slam.run.team_link.member import MID_RANGE, MemberCheckpoints
    from swarmsplat.slam.run.team_link.server_node import ServerNode

    cfg, cam = SlamConfig(), PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60)
    wire = _Wire()
    node = AgentNode(cam, cfg, "a", wire)
    node.start(4)
    kf = lambda mid, i: L.KeyframeMeta(mid=mid, id=i, frame_index=2 * i, timestamp=0.1 * i,  # noqa: E731
                                       T_local_cam=np.eye(4)[None], odom_T=np.eye(4)[None] if i else np.zeros((0, 4, 4)),
                                       odom_info=np.eye(6)[None] if i else np.zeros((0, 6, 6)))
    frames = lambda mid, idx: L.Frames(mid=mid, rounds_done=len(idx), keyframes=1, frame_index=np.array(idx),  # noqa: E731
                                       timestamp=0.1 * np.array(idx, float), submap_id=np.zeros(len(idx), np.int64),
                                       T_local_cam=np.repeat(np.eye(4)[None], len(idx), 0))
    node.outbox.put(kf(node.outbox.next_mid(), 0))
    saved = pickle.dumps(node)  # a checkpoint with Join and keyframe 0 queued (mids 1, 2)
    killed = [kf(3, 1), frames(4, [0, 1, 2])]  # what the killed process sent after it

    ckpt = MemberCheckpoints(tmp_path, {}, cfg)
    assert (ckpt._next_epoch(), ckpt._next_epoch()) == (MID_RANGE, 2 * MID_RANGE)  # one range per restart
    wire2 = _Wire()
    resumed = pickle.loads(saved)
    assert resumed.tx is None and resumed.journal is None and not resumed.welcomed
    resumed.reattach(wire2, None, MID_RANGE)
    resumed.service()
    assert [m.mid for m in wire2.sent] == [1, 2]  # the queue, sent again at once under its ids
    again = [kf(resumed.outbox.next_mid(), 1), frames(resumed.outbox.next_mid(), [0, 1, 2, 3])]
    assert [m.mid for m in again] == [MID_RANGE + 1, MID_RANGE + 2]

    team = Team([cam], ["a"], cfg, agent_class=AgentMirror)
    server = ServerNode(team, _Wire(), say=lambda *a: None)
    for msg in [wire.sent[0], wire.sent[1], *killed, *wire2.sent, *again]:
        server.handle(0, msg)
    p = server.peers[0]
    assert sorted(p.meta) == [0, 1] and p.repeats == 1 and p.duplicates == 2
    assert [r.frame_index for r in team.agents[0].poses] == [0, 1, 2, 3]  # frame 3 is new, 0-2 kept once


def test_a_server_killed_twice_replays_every_whole_record(tmp_path):
    """A kill while a record is appended leaves it cut; the restarted server drops it from the journal before it
    appends, so a server restarted again still replays every acknowledged message."""
    import numpy as np

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.run.team_link import messages as L
    from swarmsplat.slam.run.team_link.server_node import ServerNode

    cfg, cam = SlamConfig(), PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60)
    journal = tmp_path / "link" / "journal.bin"
    frames = lambda mid, idx: L.Frames(mid=mid, rounds_done=idx + 1, keyframes=0, frame_index=np.array([idx]),  # noqa: E731
                                       timestamp=np.array([0.1 * idx]), submap_id=np.zeros(1, np.int64),
                                       T_local_cam=np.eye(4)[None])
    server = lambda: ServerNode(Team([cam], ["a"], cfg, agent_class=AgentMirror), _Wire(), journal=journal,  # noqa: E731
                                say=lambda *a: None)
    first = server()
    for i in range(2):
        first.handle(0, frames(i + 1, i))
        first.poll()
    first._journal.close()
    record = L.LINK.encode(frames(3, 2), 1, 0)
    with open(journal, "ab") as f:  # killed half-way through the third record (not acknowledged)
        f.write(len(record).to_bytes(4, "little") + record[: len(record) // 2])
    second = server()
    assert second.replayed == 2
    second.handle(0, frames(3, 2))  # resent by the agent
    second.poll()
    second._journal.close()
    third = server()
    assert third.replayed == 3 and [r.frame_index for r in third.team.agents[0].poses] == [0, 1, 2]
