"""Place recognition: VLAD (default, no weights), CosPlace and NetVLAD architectures, cosine database."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.place_recognition import PAPER_THRESHOLD, PlaceDatabase, make_recognizer
from swarmsplat.registration.place_recognition.vlad import VLADRecognizer
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose


# Tiny tensors: torch's intra-op threads only add wake-up latency on a busy 2-core machine.
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def views():
    """Two rooms; in room A three places, each seen twice with a small motion."""
    cam = default_camera(240, 180)
    room_a, room_b = TexturedRoom(seed=1), TexturedRoom(seed=2)
    places = [((0.0, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), 180.0), ((0.5, 0.0, 0.5), 90.0)]
    a = [room_a.render(look_pose(p, yaw), cam)[0] for p, yaw in places]
    a2 = [room_a.render(look_pose(np.add(p, (0.15, 0.0, 0.1)), yaw + 5.0), cam)[0] for p, yaw in places]
    b = [room_b.render(look_pose(p, yaw), cam)[0] for p, yaw in places]
    return a, a2, b


@pytest.fixture(scope="module")
def vlad(views):
    a, a2, b = views
    return VLADRecognizer(n_clusters=16).fit(a + b, seed=3)


def test_vlad_descriptor_is_unit_float32_of_known_size(vlad, views):
    d = vlad.describe(views[0][0])
    assert d.dtype == np.float32 and d.shape == (vlad.dim,) == (16 * 128,)
    assert abs(np.linalg.norm(d) - 1.0) < 1e-5
    assert vlad.descriptor_bytes == d.nbytes == 16 * 128 * 4


def test_vlad_similar_places_score_higher_than_dissimilar(vlad, views):
    a, a2, b = views
    da, da2, db = vlad.describe_many(a), vlad.describe_many(a2), vlad.describe_many(b)
    sim = da @ da2.T  # [place, revisit]
    for i in range(len(a)):
        others = np.delete(sim[i], i)
        assert sim[i, i] > others.max(), f"place {i}: same place {sim[i, i]:.3f} vs others {others}"
        assert sim[i, i] > (da[i] @ db.T).max()  # other room


def test_vlad_training_is_deterministic_and_vocabulary_round_trips(vlad, views, tmp_path):
    a, _, b = views
    again = VLADRecognizer(n_clusters=16).fit(a + b, seed=3)
    np.testing.assert_array_equal(again.centroids, vlad.centroids)
    path = vlad.save(tmp_path / "vocab.npz")
    loaded = make_recognizer("vlad", checkpoint=str(path))
    np.testing.assert_array_equal(loaded.describe(a[1]), vlad.describe(a[1]))


def test_vlad_bad_inputs(vlad):
    with pytest.raises(InputError, match="not trained"):
        VLADRecognizer().describe(np.zeros((64, 64, 3), np.uint8))
    assert not np.any(vlad.describe(np.full((64, 64, 3), 128, np.uint8)))  # blank/grey: zero vector, never a match
    assert vlad.describe(np.full((64, 64), 7, np.uint8)).shape == (vlad.dim,)  # single-channel accepted
    for bad, msg in [(np.zeros((64, 64, 3), np.uint16), "uint16"), (np.zeros((64, 64, 5), np.uint8), "shape"),
                     (np.zeros((8, 8, 3), np.uint8), "too small"), (np.zeros((2, 64, 64, 3), np.uint8), "shape"),
                     ([[1, 2]], "numpy array")]:
        with pytest.raises(InputError, match=msg):
            vlad.describe(bad)
    with pytest.raises(InputError, match="features"):
        VLADRecognizer(n_clusters=16).fit([np.zeros((64, 64, 3), np.uint8)])


def _unit(v):
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v)


def test_database_nearest_neighbour_threshold_topk_and_exclusion():
    db = PlaceDatabase(3)
    db.add_many("a", [0, 1, 2, 3], [_unit([1, 0, 0]), _unit([1, 0.1, 0]), _unit([0, 1, 0]), _unit([1, 0.05, 0])])
    db.add_many("b", [0, 1], [_unit([1, 0.02, 0]), _unit([0, 0, 1])])
    q = _unit([1, 0.01, 0])
    top = db.query(q, k=3)
    assert [(m.agent, m.index) for m in top] == [("a", 0), ("b", 0), ("a", 3)]
    assert all(x.similarity >= y.similarity for x, y in zip(top, top[1:]))
    # exclusion window: a's own neighbours of keyframe 1 (0..2 with window 1) are skipped
    got = db.query(q, query_agent="a", query_index=1, k=2, exclusion_window=1)
    assert [(m.agent, m.index) for m in got] == [("b", 0), ("a", 3)]
    assert all(m.agent == "b" for m in db.query(q, query_agent="a", k=5, other_agents_only=True))
    assert db.query(_unit([0, 0, 1]), k=5, threshold=0.9) == db.query(_unit([0, 0, 1]), k=1)
    # per-keyframe nearest neighbour between agents, with the paper's permissive threshold
    cands = db.candidates("b", [0, 1], np.stack([_unit([1, 0.02, 0]), _unit([0, 0, 1])]), threshold=PAPER_THRESHOLD)
    assert [(c.query_index, c.agent, c.index) for c in cands] == [(0, "a", 0)]  # b1 has nothing above 0.1 in a
    db.add("c", 0, _unit([1, 0.03, 0]))
    only_c = db.candidates("b", [0], [_unit([1, 0.02, 0])], agents=["c"])
    assert [(c.agent, c.index) for c in only_c] == [("c", 0)]
    with pytest.raises(InputError, match=r"shape \[3\]"):
        db.add("a", 9, np.ones(4))


def test_zero_descriptor_never_matches():
    db = PlaceDatabase(2)
    db.add("a", 0, np.zeros(2))
    assert db.query(_unit([1, 0]), threshold=PAPER_THRESHOLD) == []


# ---- CosPlace / NetVLAD: the published architectures on tiny inputs, checkpoints from a path ---------------------

def test_cosplace_keys_match_the_published_layout_and_checkpoint_loads(tmp_path):
    from swarmsplat.registration.place_recognition.cosplace import CosPlaceNet, CosPlaceRecognizer

    torch.manual_seed(0)
    net = CosPlaceNet("ResNet18", 32)
    keys = list(net.state_dict())
    for k in ["backbone.0.weight", "backbone.1.running_var", "backbone.4.0.conv1.weight", "backbone.5.0.downsample.0.weight",
              "backbone.7.1.bn2.bias", "aggregation.1.p", "aggregation.3.weight", "aggregation.3.bias"]:
        assert k in keys
    assert not any(k.startswith("backbone.8") for k in keys)  # avgpool/fc removed
    r50 = CosPlaceNet("ResNet50", 64).state_dict()
    assert tuple(r50["aggregation.3.weight"].shape) == (64, 2048) and "backbone.4.0.conv3.weight" in r50
    path = tmp_path / "ResNet18_32_cosplace.pth"
    torch.save(net.state_dict(), path)
    rec = CosPlaceRecognizer.from_checkpoint(path, backbone="ResNet18", dim=32, resize=(64, 64))
    img = np.random.default_rng(0).integers(0, 255, (50, 70, 3), dtype=np.uint8)
    d = rec.describe(img)
    assert d.shape == (32,) and d.dtype == np.float32 and abs(np.linalg.norm(d) - 1) < 1e-5
    ref = CosPlaceRecognizer(net, resize=(64, 64)).describe(img)
    np.testing.assert_allclose(d, ref, atol=1e-6)
    np.testing.assert_array_equal(rec.describe(img), d)  # deterministic


def test_learned_recognizers_without_checkpoint_say_so_in_one_line(tmp_path):
    for name in ("cosplace", "netvlad"):
        with pytest.raises(InputError) as e:
            make_recognizer(name)
        assert "checkpoint" in str(e.value) and "\n" not in str(e.value)
        with pytest.raises(InputError, match="not found"):
            make_recognizer(name, checkpoint=str(tmp_path / "missing.pth"))
    bad = tmp_path / "wrong.pth"
    torch.save({"x": torch.zeros(1)}, bad)
    with pytest.raises(InputError, match="does not fit"):
        make_recognizer("cosplace", checkpoint=str(bad), backbone="ResNet18", dim=32)


def test_netvlad_keys_and_wrapped_checkpoint(tmp_path):
    from swarmsplat.registration.place_recognition.netvlad import NetVLADNet, NetVLADRecognizer

    torch.manual_seed(0)
    net = NetVLADNet(num_clusters=4)
    sd = net.state_dict()
    convs = sorted({int(k.split(".")[1]) for k in sd if k.startswith("encoder.")})
    assert convs == [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]  # VGG16 features[:-2]
    assert tuple(sd["pool.conv.weight"].shape) == (4, 512, 1, 1) and tuple(sd["pool.centroids"].shape) == (4, 512)
    path = tmp_path / "checkpoint.pth.tar"  # the released files wrap the weights and may carry DataParallel names
    torch.save({"epoch": 1, "state_dict": {k.replace("encoder.", "encoder.module."): v for k, v in sd.items()}}, path)
    rec = NetVLADRecognizer.from_checkpoint(path, num_clusters=4, resize=(64, 48))
    img = np.random.default_rng(1).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    d = rec.describe(img)
    assert d.shape == (4 * 512,) and abs(np.linalg.norm(d) - 1) < 1e-5
    np.testing.assert_allclose(d, NetVLADRecognizer(net, resize=(64, 48)).describe(img), atol=1e-6)


def test_bow_scores_are_nonnegative_and_rank_revisits_first(views, tmp_path):
    from swarmsplat.registration.place_recognition.vlad import BoWRecognizer

    a, a2, b = views
    bow = BoWRecognizer(n_clusters=64).fit(a + b, seed=0)
    assert bow.dim == 64 and bow.descriptor_bytes == 256
    da, da2, db = bow.describe_many(a), bow.describe_many(a2), bow.describe_many(b)
    sim = da @ da2.T
    assert (sim >= 0).all() and (da @ db.T >= 0).all()
    for i in range(len(a)):
        assert sim[i, i] > np.delete(sim[i], i).max() and sim[i, i] > (da[i] @ db.T).max()
        assert sim[i, i] > PAPER_THRESHOLD
    path = bow.save(tmp_path / "bow.npz")
    np.testing.assert_array_equal(make_recognizer("bow", checkpoint=str(path)).describe(a[0]), da[0])
    with pytest.raises(InputError, match="is a bow vocabulary"):
        make_recognizer("vlad", checkpoint=str(path))


def test_thumbnail_descriptor_needs_no_vocabulary_and_tells_revisits_apart():
    from swarmsplat.registration.place_recognition import make_recognizer

    rec = make_recognizer("thumbnail")
    rng = np.random.default_rng(5)
    a = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
    a_noisy = np.clip(a.astype(int) + rng.integers(-8, 9, size=a.shape), 0, 255).astype(np.uint8)
    b = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
    da, dn, db = rec.describe(a), rec.describe(a_noisy), rec.describe(b)
    assert da.shape == (rec.dim,) and da.dtype == np.float32 and rec.descriptor_bytes == 4 * rec.dim
    assert abs(np.linalg.norm(da) - 1) < 1e-5
    assert float(da @ dn) > 0.95 > float(da @ db)
