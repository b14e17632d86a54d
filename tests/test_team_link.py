"""The GRAND-SLAM team across processes over Zenoh on localhost: `run --processes` writes the in-process team's
outputs byte for byte (a generated sequence split in two, so the agents join and the server sends corrections),
with the link's bytes in metrics.json; and a team whose server is killed (SIGKILL) mid-run and started again on
the same folder still finishes with the same outputs: the agents keep tracking, queue and resend, and the server
replays its journal. Skipped without eclipse-zenoh."""

from __future__ import annotations

import filecmp
import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.flocc.swarm.zenoh_transport import zenoh_available

pytestmark = pytest.mark.skipif(not zenoh_available(), reason="eclipse-zenoh is not installed")

SPLIT = "0:5,2:8"
# a lossless link: the in-process team's outputs byte for byte
LOSSLESS = {"images": "lossless", "gaussians": "float32", "cull_gaussians": False}
FAST = {  # as tests/test_team.py: the team's logic, not the map's quality
    "mapping": {"iterations": 8, "first_iterations": 25},
    "tracking": {"refine": False},
    "keyframes": {"every": 2},
    "loop_closure": {"min_index_gap": 2},
    "server": {"tau_sim": 0.5},
    "team": {"render_views": 2},
    "link": {"resend_s": 1.0, "agent_timeout_s": 60.0, "finish_timeout_s": 60.0, **LOSSLESS},
}
SAME = ["loops.csv", "map.ply", "pose_graph_initial.g2o", "pose_graph_optimized.g2o", "trajectories/agent_0.txt",
        "trajectories/agent_1.txt", "trajectories_no_lc/agent_0.txt", "trajectories_no_lc/agent_1.txt"]


@pytest.fixture(scope="module")
def team_run(tmp_path_factory):
    """The generated sequence, the config as a file, and the in-process team's outputs on its split."""
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.datasets.split import parse_ranges, split_sequence
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("team_link")
    data = generate(root / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=8))
    cfg = SlamConfig().override(FAST)
    (root / "cfg.yaml").write_text(cfg.to_yaml())
    ds = split_sequence(load_dataset(data).agents[0], parse_ranges(SPLIT))
    # The in-process team in a process of its own, as `swarmsplat run` runs it: a run's last bits depend on state
    # that other tests leave in this process (a fresh pytest process gives the agents' processes' map byte for
    # byte, the full suite's process one Gaussian fewer).
    subprocess.run([sys.executable, "-m", "swarmsplat.slam", "run", str(data), "--split", SPLIT, "--config",
                    str(root / "cfg.yaml"), "--out", str(root / "in_process"), "--quiet"], check=True,
                   capture_output=True)
    m = json.loads((root / "in_process" / "metrics.json").read_text())
    return root, data, cfg, ds, m


def _metrics_equal(a: dict, b: dict) -> None:
    for k in ("ate_rmse_team", "psnr", "ssim", "depth_l1", "loops", "loop_candidates", "gaussians",
              "pose_graph_optimisations", "components", "all_agents_joined"):
        assert a[k] == b[k], k
    for x, y in zip(a["agents"], b["agents"]):
        for k in ("name", "frames_tracked", "keyframes", "submaps", "gaussians", "ate_rmse", "psnr",
                  "skipped_frames"):
            assert x[k] == y[k], (x["name"], k)


def test_run_processes_writes_the_in_process_outputs(team_run, tmp_path):
    from swarmsplat.slam.run.team_link.processes import run_team_processes

    root, data, cfg, ds, m_in = team_run
    assert m_in["loops_accepted"] >= 1 and m_in["all_agents_joined"], "the split must join (corrections are sent)"
    out = tmp_path / "processes"
    m = run_team_processes(data, out, cfg, split=SPLIT, loaded=ds, progress=False, timeout=120)
    for f in SAME:
        assert filecmp.cmp(root / "in_process" / f, out / f, shallow=False), f
    saved = json.loads((out / "metrics.json").read_text())
    _metrics_equal(m_in, saved)
    assert set(saved) - set(m_in) == {"link"}
    link = saved["link"]
    assert link["lost_agents"] == [] and link["replayed_messages"] == 0
    for name, s in link["agents"].items():
        agent = next(a for a in saved["agents"] if a["name"] == name)
        assert s["keyframes"] == agent["keyframes"] and s["submaps"] == agent["submaps"]
        assert {"Join", "KeyframeMeta", "KeyframeImage", "Frames", "SubmapData", "Done"} <= set(s["bytes_from_agent"])
        assert {"Welcome", "Ack", "Correction"} <= set(s["bytes_to_agent"])
        assert 0 < s["bytes_per_keyframe"] and 0 < s["bytes_per_submap"]
        assert s["bytes_total"] == sum(s["bytes_from_agent"].values()) + sum(s["bytes_to_agent"].values())
        # against the keyframes it sent, raw: 8-bit RGB + 16-bit depth at the size of its input frames
        w, h = ds.agents[0].camera.width, ds.agents[0].camera.height
        assert s["input_size"] == [w, h] and s["raw_keyframe_bytes"] == w * h * 5 == link["raw_keyframe_bytes"]
        assert s["fraction_of_raw"] == pytest.approx(s["bytes_total"] / (w * h * 5 * s["keyframes"]))
        assert s["raw_rgbd_640x480_bytes"] == 640 * 480 * 5 * s["keyframes"]
        assert s["agent_side"]["resent"] == 0 and s["dropped_images"] == 0
    assert "## Link" in (out / "report.md").read_text()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_server_killed_mid_run_restarts_from_its_journal(team_run, tmp_path):
    """kill -9 of the server once it has journaled some keyframes; the agents lose the link, keep going, resend;
    a new server on the same --out replays its journal and the run ends with the in-process outputs."""
    root, data, cfg, ds, m_in = team_run
    port, out = _free_port(), tmp_path / "restart"
    endpoint = f"tcp/127.0.0.1:{port}"
    run = f"k{os.getpid()}"
    base = [sys.executable, "-m", "swarmsplat.slam"]
    server = base + ["server", "--agents", "2", "--out", str(out), "--config", str(root / "cfg.yaml"), "--dataset",
                     str(data), "--split", SPLIT, "--listen", endpoint, "--run", run, "--quiet"]
    agents = [base + ["agent", str(data), "--split", SPLIT, "--id", str(k), "--name", f"agent_{k}", "--server",
                      endpoint, "--config", str(root / "cfg.yaml"), "--run", run, "--quiet"] for k in (0, 1)]
    srv = subprocess.Popen(server, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    procs = [subprocess.Popen(a, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for a in agents]
    journal = out / "link" / "journal.bin"
    try:
        t_end = time.time() + 60
        while time.time() < t_end and not (journal.is_file() and journal.stat().st_size > 50_000):
            time.sleep(0.05)
        assert journal.is_file(), "the server journaled nothing"
        srv.send_signal(signal.SIGKILL)
        srv.wait(10)
        time.sleep(2.0)  # the agents go on alone: they keep tracking and queue
        srv = subprocess.Popen(server, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _, err = srv.communicate(timeout=150)
        assert srv.returncode == 0, err[-2000:]
        for p in procs:
            p.wait(60)
    finally:
        for p in [srv, *procs]:
            if p.poll() is None:
                p.kill()
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["link"]["replayed_messages"] > 0
    for f in SAME:
        assert filecmp.cmp(root / "in_process" / f, out / f, shallow=False), f
    _metrics_equal(m_in, saved)
