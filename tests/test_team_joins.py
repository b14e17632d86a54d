"""Joining two agents' frames (slam.dense.team.server): a verified loop between agents in different frames waits
for a second one that implies the same alignment (server.join_min_loops = 2) and shares no keyframe with it; a
loop that disagrees is refused once the frames are joined; a join whose every supporting loop is later rejected
is undone. The server runs here on stub agents whose keyframe poses are known exactly."""

from __future__ import annotations

from types import SimpleNamespace as NS

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.loops.loop_log import INTER, LoopRecord
from swarmsplat.slam.dense.team.server import InterLoop, Server, ServerConfig

RNG = np.random.default_rng(7)
N_KF = 6
# The true pose of each agent's world frame in agent 0's world frame (the alignment a join must find).
TRUE = [np.eye(4), se3.exp(np.array([0.1, -0.4, 0.2, 1.5, -0.3, 0.4])), se3.exp(np.array([-0.2, 0.3, 0.1, -1.0, 0.8, 0.1]))]
WORLD = [[se3.exp(RNG.normal(size=6) * [0.3, 0.3, 0.3, 1.0, 1.0, 0.3]) for _ in range(N_KF)] for _ in TRUE]


def _server(n_agents: int = 2, **cfg) -> Server:
    agents = [NS(name=f"agent_{a}", keyframes=[NS(id=k, frame_index=k) for k in range(N_KF)], gmap=None,
                 cfg=SlamConfig()) for a in range(n_agents)]
    srv = Server(agents, ServerConfig(coarse="fpfh", **cfg))
    srv.global_pose = lambda a, kf: srv.slots[a].T_global_world @ WORLD[a][kf.id]
    return srv


def _loop(srv: Server, b: int, m: int, a: int, q: int, error: np.ndarray | None = None) -> InterLoop:
    """Agent a's keyframe q seen from agent b's keyframe m, as the true geometry gives it (times `error`)."""
    T = se3.inverse(TRUE[b] @ WORLD[b][m]) @ TRUE[a] @ WORLD[a][q]
    if error is not None:
        T = T @ error
    rec = LoopRecord(INTER, f"agent_{a}", q, q, f"agent_{b}", m, m, 0.5)
    srv.records.append(rec)
    return InterLoop(b, m, a, q, T, rec)


def _offer(srv: Server, L: InterLoop) -> LoopRecord:
    return srv._join_or_wait(L, "test")


def test_first_loop_waits_and_a_consistent_second_joins():
    srv = _server()
    first = _offer(srv, _loop(srv, 0, 1, 1, 2))
    assert not first.accepted and first.reason_code == "unconfirmed" and srv.components() == {0: [0], 1: [1]}
    second = _offer(srv, _loop(srv, 0, 3, 1, 4))
    assert second.accepted and second.joined and first.accepted and not first.joined
    assert srv.components() == {0: [0, 1]} and srv.joins == 1 and not srv.pending
    np.testing.assert_allclose(srv.slots[1].T_global_world, TRUE[1], atol=1e-9)
    assert len(srv.inter) == 2


def test_loops_sharing_a_keyframe_are_not_independent_evidence():
    srv = _server()
    _offer(srv, _loop(srv, 0, 1, 1, 2))
    rec = _offer(srv, _loop(srv, 0, 3, 1, 2))  # the same query keyframe
    assert not rec.accepted and srv.components() == {0: [0], 1: [1]} and len(srv.pending) == 2


def test_a_disagreeing_loop_never_joins_and_is_refused_after_the_join():
    srv = _server()
    _offer(srv, _loop(srv, 0, 1, 1, 2))
    off = se3.exp(np.array([0.0, 0.0, 0.15, 0.4, 0.0, 0.0]))  # 40 cm and 8.6 deg away from the truth
    bad = _offer(srv, _loop(srv, 0, 3, 1, 4, error=off))
    assert not bad.accepted and srv.components() == {0: [0], 1: [1]}
    good = _offer(srv, _loop(srv, 0, 5, 1, 0))
    assert good.joined and srv.components() == {0: [0, 1]}
    assert not bad.accepted and bad.reason_code == "inconsistent" and "joined frames" in bad.reason
    np.testing.assert_allclose(srv.slots[1].T_global_world, TRUE[1], atol=1e-9)


def test_the_tolerance_decides_agreement():
    small = se3.exp(np.array([0.0, 0.0, 0.005, 0.03, 0.0, 0.0]))  # 3 cm, 0.3 deg: drift-sized
    srv = _server()
    _offer(srv, _loop(srv, 0, 1, 1, 2))
    assert _offer(srv, _loop(srv, 0, 3, 1, 4, error=small)).joined
    srv = _server(join_tolerance_trans=0.01)
    _offer(srv, _loop(srv, 0, 1, 1, 2))
    assert not _offer(srv, _loop(srv, 0, 3, 1, 4, error=small)).accepted


def test_one_loop_joins_at_once_when_configured():
    srv = _server(join_min_loops=1)
    rec = _offer(srv, _loop(srv, 0, 1, 1, 2))
    assert rec.accepted and rec.joined and srv.components() == {0: [0, 1]}


def test_join_without_its_loops_is_undone_and_keeps_the_rest_in_place():
    """Agents 0-1 and 1-2 joined; every 0-1 loop is then rejected: {1, 2} split off with 1 as its root, the
    relative pose of 1 and 2 unchanged, agent 0 untouched."""
    srv = _server(3)
    for L in (_loop(srv, 0, 1, 1, 2), _loop(srv, 0, 3, 1, 4), _loop(srv, 1, 0, 2, 1), _loop(srv, 1, 5, 2, 3)):
        _offer(srv, L)
    assert srv.components() == {0: [0, 1, 2]} and srv.joins == 2
    rel = se3.inverse(srv.slots[1].T_global_world) @ srv.slots[2].T_global_world
    for k, L in enumerate(srv.inter):
        if {L.agent_i, L.agent_j} == {0, 1}:
            srv._reject_edge(("inter", k), "inconsistent", "inconsistent after optimisation (test)")
    assert srv._split_unsupported() == 1 and srv.joins_undone == 1
    assert srv.components() == {0: [0], 1: [1, 2]}
    np.testing.assert_allclose(srv.slots[1].T_global_world, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(srv.slots[2].T_global_world, rel, atol=1e-9)
    np.testing.assert_allclose(srv.slots[0].T_global_world, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("bad", [{"join_min_loops": 0}, {"join_min_loops": 3}, {"join_tolerance_trans": 0.0},
                                 {"top_k": 0}, {"coarse_width": 8}])
def test_bad_join_settings_are_refused(bad):
    from swarmsplat.kernels.errors import InputError

    key = next(iter(bad))
    with pytest.raises(InputError, match=f"server.{key}"):
        SlamConfig().override({"server": bad})
