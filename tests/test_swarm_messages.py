"""Swarm messages: every type round-trips; foreign, malformed, truncated and wrong-version bytes are rejected."""

import json
import struct

import numpy as np
import pytest

from swarmsplat.slam.flocc.swarm import messages as M


def _samples():
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (2, 1, 1))
    loops = dict(query_robot=np.array([0, 0]), query_index=np.array([3, 4]), match_robot=np.array([1, 2]),
                 match_index=np.array([5, 6]), T_query_match=T, confidence=np.array([0.5, 0.9]),
                 odom_scale=np.array([0.3, 0.4]))
    return [
        M.Hello(tick=3, n_keyframes=5, have_desc={"1": 4}, loops_with={"1": 77}, graph_version=[5, 123],
                graphs_held={"2": [3, 9]}, estimate_stamp=[10, 2, 1, 3]),
        M.Descriptors(owner=1, indices=np.arange(3), descriptors=rng.normal(size=(3, 8)).astype(np.float32)),
        M.EncodingRequest(owner=2, indices=np.array([1, 7])),
        M.EncodingReply.pack(2, [100.0, 100.0, 50.0, 50.0, 100, 80], {1: b"abc", 7: b"\x00" * 10}),
        M.LoopBatch(version=[3, 4, 5], **loops),
        M.GraphSubmission(robot=1, version=[4, 99], odometry=np.tile(np.eye(4), (4, 1, 1)), **loops),
        M.Estimate(leader=0, anchor=0, stamp=[8, 2, 1, 5], basis={"0": [4, 1], "1": [4, 2]}, formulation="is",
                   solver="lm", robots=np.array([0, 1]), counts=np.array([4, 4]), poses=np.tile(np.eye(4), (8, 1, 1)),
                   scales=np.array([1.5])),
    ]


@pytest.mark.parametrize("msg", _samples(), ids=lambda m: m.kind)
def test_round_trip(msg):
    data = M.encode(msg, sender=3, seq=42)
    h, back = M.decode(data)
    assert (h.type_id, h.sender, h.seq) == (msg.TYPE, 3, 42)
    assert type(back) is type(msg)
    for k in msg.SCALARS:
        assert getattr(back, k) == getattr(msg, k)
    for k, (dt, _) in msg.ARRAYS.items():
        a, b = np.asarray(getattr(msg, k)), getattr(back, k)
        assert b.dtype == np.dtype(dt) and b.shape == a.shape and np.array_equal(a, b)
    assert len(data) >= M.HEADER_BYTES


def test_encoding_reply_items():
    r = M.EncodingReply.pack(1, [1, 1, 1, 1, 1, 1], {4: b"xy", 2: b"z"})
    _, back = M.decode(M.encode(r, 1, 1))
    assert back.items() == {2: b"z", 4: b"xy"}


def _bad(data):
    with pytest.raises(M.MessageError):
        M.decode(data)


def test_rejects_foreign_and_malformed():
    good = M.encode(_samples()[1], 1, 1)
    _bad(b"")
    _bad(b"GET / HTTP/1.1\r\n\r\n" + b"x" * 20)  # foreign
    _bad(b"XXXX" + good[4:])  # foreign magic
    _bad(good[:4] + bytes([M.SCHEMA_VERSION + 1]) + good[5:])  # another schema version
    _bad(good[:5] + bytes([250]) + good[6:])  # unknown type
    _bad(good[:-1])  # truncated
    _bad(good + b"\x00")  # padded
    _bad(good[:30] + b"\xff" * 10 + good[40:])  # corrupt JSON header


def _rebuild(msg, mutate):
    """Re-encode `msg` with its JSON header changed by `mutate(head)`; lengths are fixed up, so only the
    content is wrong."""
    data = M.encode(msg, 1, 1)
    body = data[M.HEADER_BYTES:]
    (n,) = struct.unpack_from("<I", body)
    head = json.loads(body[4:4 + n])
    mutate(head)
    new = json.dumps(head).encode()
    payload = struct.pack("<I", len(new)) + new + body[4 + n:]
    return data[:M.HEADER_BYTES - 4] + struct.pack("<I", len(payload)) + payload


def test_rejects_wrong_fields_types_and_shapes():
    hello, desc, est = _samples()[0], _samples()[1], _samples()[6]
    _bad(_rebuild(hello, lambda h: h["s"].pop("tick")))  # missing field
    _bad(_rebuild(hello, lambda h: h["s"].update(tick="3")))  # wrong type
    _bad(_rebuild(hello, lambda h: h["s"].update(extra=1)))  # unknown field
    _bad(_rebuild(hello, lambda h: h["s"].update(have_desc={"1": "many"})))  # nested type
    _bad(_rebuild(desc, lambda h: h["a"][1].__setitem__(1, "<f8")))  # dtype differs from the schema
    _bad(_rebuild(desc, lambda h: h["a"][1].__setitem__(1, "|O")))  # object dtype: never
    _bad(_rebuild(desc, lambda h: h["a"][1].__setitem__(2, [3, 9])))  # shape claims more bytes
    _bad(_rebuild(desc, lambda h: h["a"][1].__setitem__(2, [24])))  # wrong ndim
    _bad(_rebuild(est, lambda h: h["a"][1].__setitem__(2, [3])))  # counts disagree with robots
    _bad(_rebuild(desc, lambda h: h["a"][1].pop()))  # an array spec without its shape
    _bad(_rebuild(desc, lambda h: h.update(a=[["indices"], ["descriptors"]])))  # names only
    _bad(_rebuild(est, lambda h: h["s"].update(stamp=[True, 1])))  # a bool is not a stamp integer
    deep = b"[" * 100_000  # nested past the JSON decoder's recursion limit
    payload = struct.pack("<I", len(deep)) + deep
    _bad(M.encode(hello, 1, 1)[:M.HEADER_BYTES - 4] + struct.pack("<I", len(payload)) + payload)


def test_rejects_bad_values():
    est = _samples()[6]
    est.poses = est.poses.copy()
    est.poses[0, 0, 0] = np.nan
    _bad(M.encode(est, 0, 1))
    lb = _samples()[4]
    lb.confidence = np.array([0.5, 1.5])
    _bad(M.encode(lb, 0, 1))
    sub = _samples()[5]
    sub.odometry = sub.odometry.copy()
    sub.odometry[1, :3, :3] *= 2.0  # not a rotation: a solver would choke on it
    _bad(M.encode(sub, 0, 1))
    desc = _samples()[1]
    desc.descriptors[0, 0] = np.inf
    _bad(M.encode(desc, 0, 1))
    rep = M.EncodingReply.pack(1, [1, 1, 1, 1, 1, 1], {1: b"abc"})
    rep.offsets = np.array([0, 5])
    _bad(M.encode(rep, 0, 1))


def test_sender_range_checked():
    with pytest.raises(M.InputError):
        M.encode(_samples()[0], sender=300, seq=1)
