"""Relative separator poses (graph.distributed.delta): float16 twists from the estimate the recipient holds. The
recipient decodes exactly what the sender recorded, whatever is lost, duplicated or reordered; the rounding stays
within one twist's float16 precision and does not accumulate; the team ends where absolute poses take it, on
fewer bytes."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data

from swarmsplat.graph import lie
from swarmsplat.graph.distributed.delta import Received, Sent
from swarmsplat.graph.distributed.messages import DELTA_BYTES, FLAG_DELTA, FLAG_SPARSE, Estimate
from swarmsplat.graph.distributed.robot import Settings
from swarmsplat.graph.distributed.team import Faults, solve_distributed
from swarmsplat.kernels.errors import InputError


def _walk(rng, steps, n=5):
    """Poses far from the origin that converge: each step moves them by a twist 0.7 times the last one's size."""
    T = lie.exp(np.concatenate([rng.normal(size=(n, 3)), 300 + 50 * rng.normal(size=(n, 3))], 1))
    out = [T]
    for k in range(steps):
        T = T @ lie.exp(rng.normal(size=(n, 6)) * 0.7 ** k)
        out.append(T)
    return out


@pytest.mark.parametrize("loss", [0.0, 0.4])
def test_the_recipient_decodes_what_the_sender_recorded(loss):
    rng = np.random.default_rng(3)
    keys = (1, 2, 3, 4, 5)
    tx, rx = Sent(), Received()
    wire, relative, worst = [], 0, 0.0
    for stamp, T in enumerate(_walk(rng, 40)):
        msg = Estimate(97, 98, stamp, T)
        tx.encode(msg, keys)
        relative += bool(msg.flags & FLAG_DELTA)
        data = msg.to_bytes()
        again = Estimate(97, 98, stamp, T)
        tx.encode(again, keys)
        assert again.to_bytes() == data  # a resend is the same bytes
        wire.append(data)
        if rng.random() < loss:
            continue
        for d in ([data, data] if rng.random() < 0.2 else [data]):  # duplicates
            got = Estimate.from_bytes(d)
            if rx.decode(got, keys):
                assert np.array_equal(got.poses, tx.decoded[98][stamp][1])  # bit for bit
                xi = lie.log(lie.between(T, got.poses))
                worst = max(worst, float(np.abs(xi).max()))
                tx.heard(98, stamp, rx.ack(97))  # the recipient's next estimate acks what it holds
    assert relative >= 30
    assert len(wire[-1]) < len(wire[0])
    assert worst < 2e-3  # float16: 2^-11 of the twists (at most ~3 here), never accumulated
    # late, reordered copies of old estimates decode as before or are refused; never another pose
    for stamp in rng.permutation(len(wire))[:10]:
        got = Estimate.from_bytes(wire[stamp])
        if rx.decode(got, keys):
            assert stamp not in tx.decoded[98] or np.array_equal(got.poses, tx.decoded[98][stamp][1])


def test_a_relative_estimate_without_its_base_is_refused():
    keys = (1,)
    tx, rx = Sent(), Received()
    T0 = np.eye(4)[None]
    T1 = T0 @ lie.exp(np.array([[0.1, 0, 0, 1, 0, 0]]))
    first = Estimate(97, 98, 1, T0)
    tx.encode(first, keys)
    tx.heard(98, 1, 1)  # acked, but the recipient never got it
    second = Estimate(97, 98, 2, T1)
    tx.encode(second, keys)
    assert second.flags & FLAG_DELTA and len(second.to_bytes()) == 25 + DELTA_BYTES
    assert not rx.decode(Estimate.from_bytes(second.to_bytes()), keys)
    assert rx.decode(Estimate.from_bytes(first.to_bytes()), keys) and rx.ack(97) == 1
    assert rx.decode(Estimate.from_bytes(second.to_bytes()), keys)
    bad = bytearray(second.to_bytes())
    bad[10:14] = (-1).to_bytes(4, "little", signed=True)  # relative, with no base
    with pytest.raises(InputError):
        Estimate.from_bytes(bytes(bad))


def test_relative_poses_end_where_absolute_ones_do_on_fewer_bytes():
    """blocks_world's 9 robots, and again with 30 % of the estimates lost and 30 % duplicated, shuffled."""
    from swarmsplat.graph.init import initialize
    from swarmsplat.graph.team_files import read_team

    g = read_team([shared_data("dgs_multirobot", "blocks_world", "9robots")])
    P0, _ = initialize(g, "best")
    for faults in (None, Faults(drop=0.3, duplicate=0.3, reorder=True, seed=2)):
        full = solve_distributed(g, Settings(delta=False), initial_poses=P0, max_rounds=30, faults=faults,
                                 stop_when_still=False)
        rel = solve_distributed(g, Settings(), initial_poses=P0, max_rounds=30, faults=faults, stop_when_still=False)
        assert rel.final_error <= full.final_error * 1.0005
        assert rel.bytes_total < 0.75 * full.bytes_total
        assert rel.bytes_per_separator_iteration < 20 < full.bytes_per_separator_iteration


def test_gnc_weights_are_sent_only_until_the_neighbour_holds_them():
    """Three robots with 10 % outlier loops, GNC on a short fixed plan: the same loops rejected and the same cost
    with absolute poses and every weight in every estimate as with relative poses and weights left out once held,
    on far fewer bytes."""
    from scipy.stats import chi2

    from swarmsplat.graph.distributed.gnc_plan import GncPlan
    from swarmsplat.graph.synthetic import TeamConfig, make_team

    team = make_team(TeamConfig(robots=3, length_m=120, grid_step=30.0, grid_nodes=2, target_loops=120,
                                loop_radius=8.0, outlier_fraction=0.1, seed=5))
    g = team.graph
    plan = GncPlan(ls_rounds=5, relay_rounds=3, steps=8, step_rounds=3, final_rounds=5,
                   barc=0.5 * float(chi2.ppf(0.99, 6)))
    full = solve_distributed(g, Settings(formulation="is", delta=False, gnc_plan=plan), "gnc")
    rel = solve_distributed(g, Settings(formulation="is", gnc_plan=plan), "gnc")
    assert len(full.rejected) >= 5 and rel.rejected == full.rejected
    assert abs(rel.final_error - full.final_error) <= 1e-3 * full.final_error
    assert rel.bytes_total < 0.6 * full.bytes_total


def test_twists_below_the_tolerance_go_as_zero_and_only_the_others_travel():
    """Sent's tolerance: a pose that moved by less stays the recipient's base (bit for bit); the estimate lists
    the others after a bit mask, and decodes to what the sender recorded."""
    keys = tuple(range(1, 12))
    tx, rx = Sent(tol=(1e-3, 1e-2)), Received()
    rng = np.random.default_rng(4)
    T0 = lie.exp(np.concatenate([0.3 * rng.normal(size=(11, 3)), 5 * rng.normal(size=(11, 3))], 1))
    first = Estimate(97, 98, 1, T0)
    tx.encode(first, keys)
    assert rx.decode(Estimate.from_bytes(first.to_bytes()), keys)
    tx.heard(98, 1, rx.ack(97))
    step = np.zeros((11, 6))
    step[[2, 7], 0] = 0.05  # two poses turn
    step[4, 3] = 0.2  # one moves
    step[:, 5] += 5e-3  # every translation below its tolerance, every rotation at zero
    step[9, 1] = 2e-3  # a rotation above its tolerance
    second = Estimate(97, 98, 2, T0 @ lie.exp(step))
    tx.encode(second, keys)
    assert second.flags & FLAG_SPARSE
    data = second.to_bytes()
    assert len(data) == 25 + 2 + 4 * DELTA_BYTES  # the mask (11 bits: 2 bytes) and 4 twists
    got = Estimate.from_bytes(data)
    assert rx.decode(got, keys)
    assert np.array_equal(got.poses, tx.decoded[98][2][1])
    still = [k for k in range(11) if k not in (2, 4, 7, 9)]
    assert np.array_equal(got.poses[still], rx.decoded[97][1][1][still])  # kept: the recipient's base
    assert np.abs(lie.log(lie.between(second.poses, got.poses))).max() < 1.1e-2
    # nothing moved: a mask of zeros and no twist
    third = Estimate(97, 98, 3, second.poses)
    tx.heard(98, 2, rx.ack(97))
    tx.encode(third, keys)
    assert len(third.to_bytes()) == 25 + 2 and rx.decode(Estimate.from_bytes(third.to_bytes()), keys)


def test_a_bad_pose_mask_is_refused():
    keys = tuple(range(1, 12))
    tx = Sent(tol=(1e-3, 1e-3))
    first = Estimate(97, 98, 1, np.tile(np.eye(4), (11, 1, 1)))
    tx.encode(first, keys)
    tx.heard(98, 1, 1)
    second = Estimate(97, 98, 2, first.poses.copy())
    second.poses[0] = lie.exp(np.array([[0.1, 0, 0, 0, 0, 0]]))[0]
    tx.encode(second, keys)
    data = bytearray(second.to_bytes())
    assert len(data) == 25 + 2 + DELTA_BYTES
    beyond = bytearray(data)
    beyond[26] |= 0x80  # bit 15 of an 11-pose mask
    not_relative = bytearray(data)
    not_relative[24] &= ~FLAG_DELTA  # a mask without relative poses
    more = bytearray(data)
    more[25] |= 0x02  # a second twist announced, not there
    for bad in (beyond, not_relative, more, data[:26]):
        with pytest.raises(InputError):
            Estimate.from_bytes(bytes(bad))


def test_the_tolerance_keeps_the_result_and_the_loops_on_fewer_bytes():
    """blocks_world's 9 robots (LM) and a 3-robot team with outlier loops (GNC on a plan): the default tolerance
    against none: the same cost to 0.1 %, the same loops rejected, fewer bytes."""
    from scipy.stats import chi2

    from swarmsplat.graph.distributed.gnc_plan import GncPlan
    from swarmsplat.graph.synthetic import TeamConfig, make_team

    team = make_team(TeamConfig(robots=3, length_m=120, grid_step=30.0, grid_nodes=2, target_loops=120,
                                loop_radius=8.0, outlier_fraction=0.1, seed=5))
    plan = GncPlan(ls_rounds=5, relay_rounds=3, steps=8, step_rounds=3, final_rounds=5,
                   barc=0.5 * float(chi2.ppf(0.99, 6)))
    none = solve_distributed(team.graph, Settings(formulation="is", gnc_plan=plan, sparse_tol=0.0), "gnc")
    tol = solve_distributed(team.graph, Settings(formulation="is", gnc_plan=plan), "gnc")
    assert Settings().sparse_tol > 0 and tol.rejected == none.rejected and len(none.rejected) >= 5
    assert abs(tol.final_error / none.final_error - 1) <= 1e-3
    assert tol.bytes_total < none.bytes_total
