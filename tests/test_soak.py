"""The soak harness (perf/soak.py) on a short run: a team of 3 agent processes and a server over Zenoh under an agent
killed and resumed, the server killed and restarted and the link cut, against the same seed without faults; every
invariant holds (every tracked frame's pose on disk, ATE within 10 %, PSNR within 0.5 dB, memory flat where a
process lived long enough to tell), and each check fails on outputs that break it. Skipped without eclipse-zenoh."""

from __future__ import annotations

import copy
import shutil

import pytest

from perf import soak as S
from swarmsplat.slam.flocc.swarm.zenoh_transport import zenoh_available


def test_the_schedule_comes_from_the_seed_and_has_every_kind():
    a = S.draw_schedule(7, 5.0, frames=375)
    assert a == S.draw_schedule(7, 5.0, frames=375) and a != S.draw_schedule(8, 5.0, frames=375)
    assert sorted(f["kind"] for f in a) == sorted(S.KINDS)
    assert [f["at"] for f in a] == sorted(f["at"] for f in a)
    for f in a:
        lo, hi = (0.1, 0.7) if f["kind"] in S.ON_AGENT else (0.1, 0.9)
        assert lo <= f["at"] <= hi
        if f["kind"] == "link_cut":
            assert 5 <= f["seconds"] <= 60
    assert len(S.draw_schedule(7, 60.0, frames=4500)) == 30
    assert [f["at_s"] for f in S.timed(a, 40.0)] == [round(40.0 * f["at"], 1) for f in a]  # on this machine
    short = S.draw_schedule(7, 1.5, ("agent_kill", "link_cut"), faults=2)
    assert sorted(f["kind"] for f in short) == ["agent_kill", "link_cut"]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    if not zenoh_available():
        pytest.skip("eclipse-zenoh is not installed")
    scratch = tmp_path_factory.mktemp("soak")
    return scratch, S.soak(1.25, 3, scratch, kinds=("agent_kill", "server_kill", "link_cut"), faults=3,
                           say=lambda s: None)


@pytest.mark.slow
def test_a_short_soak_keeps_every_invariant(report):
    scratch, r = report
    applied = [f for f in r["faults"] if f.get("applied")]
    assert {f["kind"] for f in applied} == {"agent_kill", "server_kill", "link_cut"}, r["faults"]
    failed = {k: v["detail"] for k, v in r["checks"].items() if v["ok"] is not True}
    if r["memory"] == []:  # every process of this short soak ended within warm-up + 20 s (a fast machine)
        assert failed.pop("memory_flat").startswith("not evaluated"), r["lives"]
    assert not failed, failed
    cut = next(f for f in applied if f["kind"] == "link_cut")
    assert cut["connections_reaching_server_during_cut"] == 0 and cut["reconnects_refused"] > 0
    assert cut["first_message_after_restore_s"] is not None
    kill = next(f for f in applied if f["kind"] == "server_kill")
    assert "replayed" in kill["team_did"]
    assert r["soak"]["replayed_messages"] > 0 and r["soak"]["frames_tracked"] == r["reference"]["frames_tracked"]


@pytest.mark.slow
def test_the_checks_fail_on_outputs_that_break_them(report, tmp_path):
    scratch, r = report
    data, server, agents = scratch / "data_soak", tmp_path / "server", [scratch / "soak" / f"agent_{k}" for k in
                                                                       range(S.AGENTS)]
    shutil.copytree(scratch / "soak" / "server", server)
    m = S._metrics(server)
    assert all(row["ok"] for row in S.check_poses(data, server, agents, m))
    traj = server / "trajectories" / "agent_1.txt"
    lines = traj.read_text().splitlines()
    traj.write_text("\n".join(lines[:5] + lines[6:]) + "\n")  # one tracked frame's pose gone
    rows = S.check_poses(data, server, agents, m)
    assert [row["server_missing"] for row in rows] == [0, 1, 0] and not rows[1]["ok"]
    traj.write_text("\n".join(lines + lines[-1:]) + "\n")  # a frame twice
    assert S.check_poses(data, server, agents, m)[1]["server_twice"] == 1

    ref = S._metrics(scratch / "reference" / "server")
    worse = copy.deepcopy(m)
    worse["ate_rmse_team"] = 1.15 * ref["ate_rmse_team"]
    worse["psnr"] = ref["psnr"] - 0.6
    checks = S.result_checks(worse, ref, rows, [], [])
    assert not any(checks[k]["ok"] for k in ("ate_within_10pct", "psnr_within_0.5dB", "poses_on_disk"))
    assert checks["memory_flat"]["ok"] is False  # a long soak must have a process life to measure
    assert S.result_checks(m, ref, rows, [], [], memory_required=False)["memory_flat"]["ok"] is None

    class Life:  # a process whose memory grows by a fifth after the warm-up
        role, pid, start, end, lines = "agent_0", 1, 0.0, 100.0, []

    samples = [{"t": float(t), "rss_mb": {"1": 500.0 + (100.0 if t > 80 else 0.0)}} for t in range(0, 100, 2)]
    leak = S.check_memory([Life()], samples, 100.0)
    assert leak and leak[0]["growth_pct"] == 20.0 and not leak[0]["ok"]
    assert S.result_checks(m, ref, rows, leak, [], memory_required=False)["memory_flat"]["ok"] is False
    flat = [{"t": float(t), "rss_mb": {"1": 500.0 + (20.0 if t > 80 else 0.0)}} for t in range(0, 100, 2)]
    assert S.result_checks(m, ref, rows, S.check_memory([Life()], flat, 100.0), [])["memory_flat"]["ok"] is True

    class Mapping(Life):  # the same growth, reported held by its status lines (its map): no leak
        lines = [(float(t), f"[agent_0] round {t}  held {300 + (100 if t > 80 else 0)} MB") for t in range(0, 100, 10)]

    grows = S.check_memory([Mapping()], samples, 100.0)
    assert grows[0]["measure"] == "beyond held" and grows[0]["growth_pct"] == 0.0 and grows[0]["ok"]
    assert grows[0]["held_end_mb"] == 400 and grows[0]["rss_peak_after_mb"] == 600

    class Leaking(Life):  # resident memory grows by 100 MB, the map by 20: 80 MB on 200 beyond it
        lines = [(float(t), f"[agent_0] round {t}  held {300 + (20 if t > 80 else 0)} MB") for t in range(0, 100, 10)]

    leaks = S.check_memory([Leaking()], samples, 100.0)
    assert leaks[0]["growth_pct"] == 40.0 and not leaks[0]["ok"]


def test_an_agent_that_sent_everything_is_not_lost_while_the_server_catches_up():
    """Found by the soak: on long sequences the agents finish, are acknowledged and end long before the server has
    handed their keyframes over; their silence past link.agent_timeout_s is no loss (a lost agent changes the
    keyframes' order and ends the run without evaluation). An agent silent before it sent everything still is."""
    import numpy as np

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.run.team_link import messages as L
    from swarmsplat.slam.run.team_link.agent_node import config_digest
    from swarmsplat.slam.run.team_link.server_node import ServerNode

    class Wire:
        def send(self, dest, msg):
            pass

        def poll(self):
            return []

    cfg, cam, now = SlamConfig(), PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60), [0.0]
    server = ServerNode(Team([cam, cam], ["a", "b"], cfg, agent_class=AgentMirror), Wire(), say=lambda *a: None,
                        clock=lambda: now[0])
    for a, name in enumerate("ab"):
        server.handle(a, L.Join(mid=1, name=name, camera=[100.0, 100.0, 40.0, 30.0, 80, 60],
                                config=config_digest(cfg), rounds=4))
    server.handle(0, L.KeyframeMeta(mid=2, id=0, frame_index=1, timestamp=0.1, round=1, T_local_cam=np.eye(4)[None],
                                    odom_T=np.zeros((0, 4, 4)), odom_info=np.zeros((0, 6, 6)),
                                    submap_start=np.zeros((0, 4, 4))))
    server.handle(0, L.Frames(mid=3, rounds_done=4, keyframes=1, dropped=[0], frame_index=np.arange(4),
                              timestamp=0.1 * np.arange(4), submap_id=np.zeros(4, np.int64),
                              T_local_cam=np.repeat(np.eye(4)[None], 4, 0)))
    server.handle(0, L.Done(mid=4, rounds=4, keyframes=1, submaps=0, frames=4))
    assert server.next_keyframe() is None  # a's keyframe of round 1 waits for b's round 1
    now[0] = cfg.link.agent_timeout_s + 1
    server.poll()
    assert [p.lost for p in server.peers] == [False, True]


def test_the_summary_of_a_team_whose_agents_were_all_lost():
    """A 20-minute soak's server reported every agent lost: their link records then have no agent side, and the
    summary says so instead of failing."""
    from swarmsplat.perf.soak import _summary

    m = {"status": "complete", "link": {"lost_agents": ["agent_0"], "agents": {"agent_0": {"agent_side": None},
                                                                             "agent_1": None}}}
    s = _summary(m)
    assert s["lost_agents"] == ["agent_0"] and s["resent"] == {"agent_0": None, "agent_1": None}
