"""The team server's order of work (slam.run.team_link.server_node): keyframes are handed to the team in the
in-process order (round, agent) whatever order their messages arrive in, so a team across processes gives the
in-process team's outputs; driven message by message, without a transport."""

from __future__ import annotations

from swarmsplat.slam.config import SlamConfig


class Wire:
    """A transport that sends nowhere and receives nothing: the tests hand the server its messages."""

    def send(self, dest, msg):
        pass

    def poll(self):
        return []


def test_a_keyframe_whose_images_are_late_holds_back_the_later_ones():
    """Found by a server killed mid-run under load: agent 0's keyframe of round 0 had its meta journaled but its images
    lost with the server; after the restart agent 1's keyframe of round 1 arrived whole, and agent 0 had reported
    later rounds, so it went first and the team's loops came out in another order than in one process. The first
    keyframe in the in-process order (round, agent) now waits for its images; a lost agent's never hold anyone."""
    import numpy as np

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.run.team_link import messages as L
    from swarmsplat.slam.run.team_link.agent_node import config_digest
    from swarmsplat.slam.run.team_link.server_node import ServerNode

    cfg, cam = SlamConfig(), PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60)
    server = ServerNode(Team([cam, cam], ["a", "b"], cfg, agent_class=AgentMirror), Wire(), say=lambda *a: None,
                        clock=lambda: 0.0)
    for a, name in enumerate("ab"):
        server.handle(a, L.Join(mid=1, name=name, camera=[100.0, 100.0, 40.0, 30.0, 80, 60],
                                config=config_digest(cfg), rounds=8))

    def meta(mid, rnd):
        return L.KeyframeMeta(mid=mid, id=0, frame_index=rnd, timestamp=0.1 * rnd, round=rnd,
                              T_local_cam=np.eye(4)[None], odom_T=np.zeros((0, 4, 4)), odom_info=np.zeros((0, 6, 6)),
                              submap_start=np.zeros((0, 4, 4)))

    def frames(mid, rounds):
        return L.Frames(mid=mid, rounds_done=rounds, keyframes=1, dropped=[], frame_index=np.arange(rounds),
                        timestamp=0.1 * np.arange(rounds), submap_id=np.zeros(rounds, np.int64),
                        T_local_cam=np.repeat(np.eye(4)[None], rounds, 0))

    server.handle(0, meta(2, 0))  # agent a's keyframe of round 0: its meta, not yet its images
    server.handle(0, frames(3, 4))  # a has reported rounds 0-3
    server.handle(1, meta(2, 1))  # b's keyframe of round 1, whole
    server.handle(1, frames(3, 2))
    server.peers[1].images[0] = object()
    assert server.peers[0].rounds_done == 4 and server.peers[1].rounds_done == 2
    assert server.next_keyframe() is None  # b's keyframe waits for a's images
    server.peers[0].images[0] = object()
    assert server.next_keyframe()[0] == 0
    server.peers[0].images.pop(0)
    server.peers[0].lost = True  # a lost agent's keyframe without images holds nobody
    assert server.next_keyframe()[0] == 1


def test_a_backlog_still_reports_publishes_and_keeps_the_deadline(monkeypatch):
    """Found by a 20-minute soak: a server that always had a keyframe waiting stayed inside one `process()` call for
    its whole life (338 s) and printed no status line, so its memory could not be measured; its feed and deadline
    waited as long. Each keyframe of a backlog now ends with the same tick as an idle loop's."""
    import pytest

    from swarmsplat.slam.run.team_link.server_node import ServerNode

    node = ServerNode.__new__(ServerNode)
    backlog = [(0, "kf")] * 3
    said, fed = [], []
    monkeypatch.setattr(ServerNode, "next_keyframe", lambda self: backlog.pop() if backlog else None)
    monkeypatch.setattr(ServerNode, "_process", lambda self, a, m: None)
    monkeypatch.setattr(ServerNode, "poll", lambda self: 0)
    monkeypatch.setattr(ServerNode, "status", lambda self: "keyframes n")
    node.say, node.feed, node.t0 = said.append, type("Feed", (), {"step": lambda self, n: fed.append(n)})(), 0.0
    node._ticking = (True, None, float("-inf"))  # a status line is due
    assert node.process() == 3
    assert len(fed) == 3 and said == ["[server] keyframes n"]  # one line per 10 s, not per keyframe
    backlog[:] = [(0, "kf")]
    node._ticking = (False, 1.0, 0.0)
    with pytest.raises(TimeoutError, match="gave up after 1 s"):
        node.process()


def test_finished_submaps_reach_the_mirror_while_the_server_serves():
    """Found by `perf team-link`: across processes the server put the agents' Gaussians into its mirrors only after the
    run, so the cloud route's render check drew empty maps and refused every wide loop (0 of 32 on the demo against
    11 of 12 in one process). A finished submap's Gaussians now reach the mirror when they arrive, or when the
    keyframe that opens the submap does; the first copy is kept."""
    import numpy as np
    import torch

    from swarmsplat.kernels.camera import PinholeCamera
    from swarmsplat.slam.dense.gaussian_map import GaussianParams, Submap
    from swarmsplat.slam.dense.team.mirror import AgentMirror
    from swarmsplat.slam.run.team import Team
    from swarmsplat.slam.run.team_link import messages as L
    from swarmsplat.slam.run.team_link.agent_node import config_digest
    from swarmsplat.slam.run.team_link.server_node import ServerNode

    cfg, cam = SlamConfig(), PinholeCamera(100.0, 100.0, 40.0, 30.0, 80, 60)
    server = ServerNode(Team([cam], ["a"], cfg, agent_class=AgentMirror), Wire(), say=lambda *a: None,
                        clock=lambda: 0.0)
    server.handle(0, L.Join(mid=1, name="a", camera=[100.0, 100.0, 40.0, 30.0, 80, 60], config=config_digest(cfg),
                            rounds=8))

    def meta(kf, submap):
        return L.KeyframeMeta(mid=10 + kf, id=kf, frame_index=kf, timestamp=0.1 * kf, round=kf, submap_id=submap,
                              T_local_cam=np.eye(4)[None], odom_T=np.zeros((0, 4, 4)), odom_info=np.zeros((0, 6, 6)),
                              submap_start=np.eye(4)[None] if submap else np.zeros((0, 4, 4)))

    def submap(sid, n):
        g = torch.Generator().manual_seed(sid)
        params = GaussianParams.from_points(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                            torch.full((n,), 0.01), 0.5)
        return L.SubmapData.pack(20 + sid, Submap(sid, np.eye(4), params, [sid]), "float32")

    mirror = server.team.agents[0]
    server._process(0, meta(0, 0))  # submap 0 opens (a keyframe without images: no loop search)
    assert len(mirror.gmap.submaps[0].params) == 0
    server.handle(0, submap(0, 5))  # finished: its Gaussians go in at once
    assert len(mirror.gmap.submaps[0].params) == 5
    server.handle(0, submap(1, 7))  # before the keyframe that opens submap 1 has been handled
    assert len(mirror.gmap.submaps) == 1
    server._process(0, meta(1, 1))
    assert len(mirror.gmap.submaps[1].params) == 7
    first = mirror.gmap.submaps[0].params
    server.handle(0, submap(0, 3))  # a repeat (a resent message) changes nothing
    server.collect_submaps()
    assert mirror.gmap.submaps[0].params is first and len(mirror.gmap.submaps[1].params) == 7
