"""Faults on the team link, injected over the in-process transport (slam.flocc.swarm.transport.InProcessNetwork):
the agents and the server of slam.run.team_link run in this process, one round at a time, with a tick clock.
Duplicated, delayed and reordered messages, and a link lost for several rounds, leave the outputs byte-identical
to the in-process team's; a queue too small for a long outage drops the oldest keyframe images and never a pose
or an edge; an agent that vanishes is reported lost and the other finishes; a server rebuilt from its journal
continues as if nothing happened; garbage bytes are counted and dropped. Over real Zenoh on localhost, a router
the link runs through stops and comes back: the same outputs, the lost messages resent."""

from __future__ import annotations

import filecmp

import pytest

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.flocc.swarm.transport import Faults, InProcessNetwork
from test_team_link import FAST as LINK_TEST_CONFIG
from test_team_link import LOSSLESS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FAST = {**LINK_TEST_CONFIG, "link": {"resend_s": 3.0, "agent_timeout_s": 8.0, **LOSSLESS}}  # ticks of the test's clock
SAME = ["loops.csv", "map.ply", "pose_graph_optimized.g2o", "trajectories/agent_0.txt", "trajectories/agent_1.txt",
        "trajectories_no_lc/agent_1.txt"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.io.datasets.split import split_sequence
    from swarmsplat.slam.run.team import run_team
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("link_faults")
    data = generate(root / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=8))
    ds = split_sequence(load_dataset(data).agents[0], [(0, 5), (2, 8)])
    cfg = SlamConfig().override(FAST)
    m = run_team(ds, root / "in_process", cfg, progress=False)
    assert m["all_agents_joined"], "the split must join (corrections are sent)"
    return root, ds, cfg, m


class Linked:
    """The team's nodes on one simulated network: `round(i)` steps every agent once and lets the server work."""

    def __init__(self, ds, cfg, faults=None, journal=None):
        from swarmsplat.slam.run.team_link import messages as L
        from swarmsplat.slam.run.team_link.agent_node import AgentNode

        self.ds, self.cfg, self.journal = ds, cfg, journal
        n = len(ds.agents)
        self.net = self._network(n + 1, faults)
        self.t = 0
        self.clock = lambda: float(self.t)
        self.server = self._server()
        self.agents = [AgentNode(s.camera, cfg, s.name, self._endpoint(k + 1, L.LINK), clock=self.clock)
                       for k, s in enumerate(ds.agents)]
        for node, s in zip(self.agents, ds.agents):
            node.start(len(s))
        self.alive = [True] * n

    def _server(self):
        from swarmsplat.slam.dense.team.mirror import AgentMirror
        from swarmsplat.slam.run.team import Team
        from swarmsplat.slam.run.team_link import messages as L
        from swarmsplat.slam.run.team_link.server_node import ServerNode

        team = Team([s.camera for s in self.ds.agents], [s.name for s in self.ds.agents], self.cfg,
                    agent_class=AgentMirror)
        return ServerNode(team, self._endpoint(0, L.LINK), journal=self.journal, say=lambda *a: None,
                          clock=self.clock)

    def _network(self, nodes: int, faults):
        return InProcessNetwork(range(nodes), faults=faults)

    def _endpoint(self, node: int, codec):
        return self.net.endpoint(node, codec)

    def _deliver(self) -> None:
        self.net.advance(self.t)

    def tick(self, k: int = 1) -> None:
        for _ in range(k):
            self.t += 1
            self._deliver()
            self.server.step()
            for node, alive in zip(self.agents, self.alive):
                if alive:
                    node.service()

    def run(self, between=None, max_ticks: int = 200) -> None:
        rounds = max(len(s) for s in self.ds.agents)
        for i in range(rounds):
            for node, s, alive in zip(self.agents, self.ds.agents, self.alive):
                if alive and i < len(s):
                    node.step_round(s, i, 1)
                    if i == len(s) - 1:
                        node.send_last(len(s))
            if between:
                between(self, i)
            self.tick()
        for _ in range(max_ticks):
            if self.server.all_ended() and all(n.settled() for n, a in zip(self.agents, self.alive) if a):
                break
            self.tick()
        assert self.server.all_ended(), self.server.status()
        self.server.collect_submaps()

    def write(self, out):
        from swarmsplat.slam.run.team import finish_team

        return finish_team(self.server.team, self.ds, out, wall_s=0.0, cpu0=0.0, render_views=2, progress=False)


def _same(root, out):
    return {f: filecmp.cmp(root / "in_process" / f, out / f, shallow=False) for f in SAME}


def test_duplicates_delays_and_reordering_change_nothing(reference, tmp_path):
    root, ds, cfg, m_in = reference
    link = Linked(ds, cfg, Faults(duplicate=0.3, delay=(0, 3), reorder=True, seed=4))
    link.run()
    m = link.write(tmp_path)
    assert all(_same(root, tmp_path).values()), _same(root, tmp_path)
    assert m["loops"] == m_in["loops"] and m["ate_rmse_team"] == m_in["ate_rmse_team"]
    dup = sum(p.recv_count.get("KeyframeMeta", 0) for r, p in link.server.tx.peer_stats.items())
    assert dup > sum(len(a.keyframes) for a in link.server.team.agents)  # duplicates did arrive


def test_the_compact_link_sends_less_and_keeps_the_team(reference, tmp_path):
    """The link's defaults (compact images and Gaussians, without what the server's overlap cull drops anyway):
    the same team (every agent joins, loops and ATE as in one process within 10 %) for a fraction of the bytes;
    the server holds fewer Gaussians than the agents made, and every agent still sends every submap."""
    root, ds, cfg, m_in = reference
    lossless = Linked(ds, cfg)
    lossless.run()
    compact = Linked(ds, cfg.override({"link": {**SlamConfig().link.model_dump(), **FAST["link"],
                                                **{k: SlamConfig().link.model_dump()[k] for k in LOSSLESS}}}))
    assert compact.cfg.link.images == "compact" and compact.cfg.link.gaussians == "compact"
    compact.run()
    m = compact.write(tmp_path)
    assert m["all_agents_joined"] and abs(m["ate_rmse_team"] - m_in["ate_rmse_team"]) <= 0.1 * m_in["ate_rmse_team"]
    assert abs(m["loops_accepted"] - m_in["loops_accepted"]) <= max(1, 0.1 * m_in["loops_accepted"])
    for kind in ("KeyframeImage", "SubmapData"):
        full = sum(p.unique_bytes.get(kind, 0) for p in lossless.server.peers)
        assert sum(p.unique_bytes.get(kind, 0) for p in compact.server.peers) < 0.5 * full, kind
    for node, mirror in zip(compact.agents, compact.server.team.agents):
        assert len(mirror.gmap.submaps) == len(node.agent.gmap.submaps)
        assert 0 < len(mirror.gmap) <= len(node.agent.gmap)


def test_lost_link_queues_and_resends(reference, tmp_path):
    """Agent 1 loses the link for four rounds (its messages then are lost on the way), keeps tracking and mapping,
    and its queue is resent when the link is back."""
    root, ds, cfg, _ = reference

    def outage(link, i):
        if i == 1:
            link.net.link_down(0, 2)
        if i == 5:
            link.net.link_up(0, 2)

    link = Linked(ds, cfg)
    link.run(outage)
    assert link.agents[1].outbox.resent > 0
    link.write(tmp_path)
    assert all(_same(root, tmp_path).values()), _same(root, tmp_path)


def test_a_full_queue_drops_the_oldest_images_never_poses(reference, tmp_path):
    root, ds, cfg, _ = reference
    small = cfg.override({"link": {"queue_mb": 0.4}})  # about two keyframes' images

    def outage(link, i):
        if i == 0:
            link.net.link_down(0, 2)
        if i == 5:
            link.net.link_up(0, 2)

    link = Linked(ds, small)
    link.run(outage)
    node, mirror = link.agents[1], link.server.team.agents[1]
    dropped = node.outbox.dropped_images
    assert dropped and dropped == sorted(dropped) and dropped[0] == 0  # the oldest first
    assert len(mirror.keyframes) == len(node.agent.keyframes)  # every keyframe pose and edge arrived
    assert len(mirror.loops.odometry) == len(node.agent.loops.odometry)
    assert [p.frame_index for p in mirror.poses] == [p.frame_index for p in node.agent.poses]
    assert link.server.link_metrics()["agents"]["agent_1"]["dropped_images"] == len(dropped)
    link.write(tmp_path)  # the run completes without those images


def test_an_agent_that_never_comes_back_is_reported_and_the_other_finishes(reference, tmp_path):
    root, ds, cfg, _ = reference

    def vanish(link, i):
        if i == 2:
            link.net.kill(2)
            link.alive[1] = False

    link = Linked(ds, cfg)
    link.run(vanish, max_ticks=40)
    assert link.server.peers[1].lost and not link.server.peers[0].lost
    assert link.server.link_metrics()["lost_agents"] == ["agent_1"]
    assert link.server.peers[0].processed == len(link.agents[0].agent.keyframes)
    from swarmsplat.slam.run.team_link.processes import _write_estimates

    link.server.collect_submaps()
    m = _write_estimates(link.server.team, tmp_path, 0.0, 0.0, {"lost_agents": ["agent_1"]})
    assert m["run"]["lost_agents"] == ["agent_1"] and m["agents"][0]["frames_tracked"] == 5
    assert (tmp_path / "trajectories" / "agent_0.txt").is_file() and (tmp_path / "loops.csv").is_file()


def test_a_server_rebuilt_from_its_journal_continues(reference, tmp_path):
    root, ds, cfg, _ = reference
    journal = tmp_path / "journal.bin"

    def restart(link, i):
        if i == 3:  # the server process is gone; a new one reads the journal
            link.server.close()
            link.server = link._server()
            assert link.server.replayed > 0

    link = Linked(ds, cfg, journal=journal)
    link.run(restart)
    link.write(tmp_path)
    assert all(_same(root, tmp_path).values()), _same(root, tmp_path)


def test_garbage_and_foreign_messages_are_counted_and_dropped(reference):
    from swarmsplat.slam.flocc.swarm import messages as SW

    root, ds, cfg, _ = reference
    link = Linked(ds, cfg)
    link.net.inject(0, b"not a message at all")
    link.net.inject(0, SW.encode(SW.Finish(tick=1), 1, 1))  # the swarm's family: another magic
    link.tick()
    assert link.server.tx.stats.rejected == 2


def test_link_messages_round_trip_and_compact_encodings():
    """Every link message decodes to what was sent; float16 Gaussians stay within half-float rounding (means
    exact); compact images keep depth within 0.5 mm; a message of another schema version is refused."""
    import numpy as np
    import torch

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.dense.frames import RGBD
    from swarmsplat.slam.dense.gaussian_map import GaussianParams, Submap
    from swarmsplat.slam.dense.packed import pack_lossy
    from swarmsplat.slam.flocc.swarm.messages import MessageError
    from swarmsplat.slam.run.team_link import messages as L

    g = torch.Generator().manual_seed(0)
    n = 50
    p = GaussianParams(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g) - 4,
                       torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
                       torch.randn(n, generator=g), torch.rand(n, 3, generator=g))
    sm = Submap(3, np.eye(4), p, keyframe_ids=[7, 8])
    for enc, tol in (("float32", 0.0), ("float16", 2e-3)):
        h, back = L.LINK.decode(L.LINK.encode(L.SubmapData.pack(5, sm, enc), 2, 9))
        q = back.params()
        assert h.sender == 2 and back.id == 3 and back.keyframe_ids == [7, 8]
        assert torch.equal(q.means, p.means)
        for name in ("log_scales", "quats", "logit_opacities", "colors"):
            assert torch.allclose(getattr(q, name), getattr(p, name), rtol=tol, atol=tol), (enc, name)
    f = RGBD((np.arange(48 * 64 * 3) % 251).astype(np.uint8).reshape(48, 64, 3),
             np.linspace(0.3, 4.0, 48 * 64, dtype=np.float32).reshape(48, 64), PinholeCamera(60, 60, 32, 24, 64, 48))
    c = pack_lossy(f, 90)
    assert np.abs(c.depth - f.depth).max() <= 5e-4 + 1e-6 and c.color.shape == f.color.shape
    data = bytearray(L.LINK.encode(L.Ack(mids=np.arange(3)), 0, 1))
    data[4] = L.SCHEMA_VERSION + 1
    with pytest.raises(MessageError, match="schema version"):
        L.LINK.decode(bytes(data))


def test_agent_ids_by_name():
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.run.team_link.registry import Registry

    r = Registry(3)  # no dataset: the lowest free index, in the order agents ask; a name asked again keeps it
    assert [r.assign(n) for n in ("robot_c", "robot_a", "robot_c", "robot_b")] == [0, 1, 0, 2]
    with pytest.raises(InputError, match="the team is full: 3 agents"):
        r.assign("robot_d")
    d = Registry(2, fixed=["agent_0", "agent_1"])  # a dataset's names keep its order, whoever asks first
    assert d.assign("agent_1") == 1 and d.assign("agent_0") == 0
    with pytest.raises(InputError, match="none of the server's dataset's agents"):
        Registry(2, fixed=["agent_0", "agent_1"]).assign("robot_x")
    assert Registry(2, taken={"robot_a": 1}).assign("robot_b") == 0  # a restarted server keeps who had what
    with pytest.raises(InputError):
        r.assign("")


# ---- over real Zenoh on localhost: the link through a router that stops and comes back ---------------------------

ROUTER = """
import sys, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:%d"]' % int(sys.argv[1]))
session = zenoh.open(conf)
print("ready", flush=True)
sys.stdin.read()  # until the test stops it
"""


class Router:
    """A Zenoh router in a process of its own on a loopback port (what `zenohd` is on a robot's network)."""

    def __init__(self, port: int):
        self.port, self.proc = port, None

    def start(self) -> None:
        import subprocess
        import sys

        self.proc = subprocess.Popen([sys.executable, "-c", ROUTER, str(self.port)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "ready", "the Zenoh router did not start"

    def stop(self) -> None:
        """As a crash or a power cut: SIGKILL, no goodbye to the sessions."""
        self.proc.kill()
        self.proc.wait(timeout=10)


class ZenohLinked(Linked):
    """The same nodes, each on a Zenoh session of its own in client mode, connected to one router only: every
    message crosses the router, so stopping it cuts every link. The nodes' clock is still the test's tick; each
    tick gives Zenoh a moment to deliver."""

    def __init__(self, ds, cfg, router_at: str):
        self.router_at, self.sessions = router_at, []
        super().__init__(ds, cfg)

    def _network(self, nodes: int, faults):
        self.nodes = list(range(nodes))
        return None

    def _endpoint(self, node: int, codec):
        from swarmsplat.slam.flocc.swarm.zenoh_transport import ZenohTransport

        tx = ZenohTransport(node, self.nodes, run="faults", codec=codec, listen=[], connect=[self.router_at],
                            block=True, mode="client")
        self.sessions.append(tx)
        return tx

    def _deliver(self) -> None:
        import time

        time.sleep(0.03)

    def connected(self, timeout: float = 20.0) -> bool:
        import time

        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if all(list(tx.session.info.routers_zid()) for tx in self.sessions):
                time.sleep(0.2)  # the subscriptions' declarations reach the router
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        for tx in self.sessions:
            tx.close()


def test_a_router_outage_over_zenoh_queues_resends_and_changes_nothing(reference, tmp_path):
    """The agents and the server talk through a real Zenoh router on localhost, which is killed after the first
    round and started again four rounds later: the agents keep tracking and mapping, what they sent meanwhile is
    lost on the way and resent once the sessions have reconnected, and the outputs are byte-identical to the
    in-process team's."""
    pytest.importorskip("zenoh")
    from test_live_zenoh import _free_port

    root, ds, cfg, _ = reference
    # the outage is in rounds, but reconnecting takes wall time: no agent may be declared lost for it
    cfg = cfg.override({"link": {"agent_timeout_s": 10_000.0}})
    router = Router(_free_port())
    router.start()
    link = None
    try:
        link = ZenohLinked(ds, cfg, f"tcp/127.0.0.1:{router.port}")
        assert link.connected(), "the nodes did not reach the router"
        received: dict[int, int] = {}

        def outage(link, i):
            if i == 1:
                router.stop()
            if i in (2, 4):  # messages the server has received, from every agent
                received[i] = sum(sum(st.recv_count.values()) for st in link.server.tx.peer_stats.values())
            if i == 5:
                router.start()
                assert link.connected(), "the nodes did not reconnect to the restarted router"

        link.run(outage, max_ticks=400)
        assert all(node.outbox.resent > 0 for node in link.agents)  # both lost messages in the outage
        assert not any(p.lost for p in link.server.peers)
        assert received[2] == received[4]  # nothing crossed while the router was down
        link.write(tmp_path)
    finally:
        if link is not None:
            link.close()
        if router.proc.poll() is None:
            router.stop()
    assert all(_same(root, tmp_path).values()), _same(root, tmp_path)

