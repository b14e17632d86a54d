"""MASt3R: the published architecture on a tiny random instance (shapes, official key layout, determinism,
encode/decode split), its checkpoint loading, reciprocal matching and pose from pointmaps."""

from __future__ import annotations

import argparse
import re

import numpy as np
import pytest
import torch

from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair import Encoding, make_registrar
from swarmsplat.registration.pair.mast3r.matching import fast_reciprocal_nns, pose_from_matches
from swarmsplat.registration.pair.mast3r.model import Mast3rConfig, Mast3rNet
from swarmsplat.registration.pair.mast3r.registrar import Mast3rRegistrar, load_mast3r_checkpoint
from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose, relative_pose

TINY = dict(enc_embed_dim=32, enc_depth=2, enc_num_heads=2, dec_embed_dim=24, dec_depth=4, dec_num_heads=2,
            local_feat_dim=8, feature_dim=16, layer_dims=(8, 8, 16, 16), img_size=64)
TINY_STRING = ("AsymmetricMASt3R(enc_depth=2, dec_depth=4, enc_embed_dim=32, dec_embed_dim=24, enc_num_heads=2, "
               "dec_num_heads=2, pos_embed='RoPE100', img_size=(64, 64), head_type='catmlp+dpt', "
               "output_mode='pts3d+desc8', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), "
               "patch_embed_cls='ManyAR_PatchEmbed', landscape_only=False, two_confs=True, "
               "desc_conf_mode=('exp', 0, inf), feature_dim=16, layer_dims=(8, 8, 16, 16))")


# Tiny tensors: torch's intra-op threads only add wake-up latency on a busy 2-core machine.
pytestmark = pytest.mark.usefixtures("one_torch_thread")


class Odd:
    """A class the safe checkpoint loader does not know."""


def tiny_net(seed: int = 0) -> Mast3rNet:
    torch.manual_seed(seed)
    return Mast3rNet(Mast3rConfig(**TINY)).eval()


# Every parameter name of the official AsymmetricMASt3R state dict, as patterns (i = block index).
OFFICIAL_KEYS = [
    r"mask_token", r"patch_embed\.proj\.(weight|bias)", r"enc_norm\.(weight|bias)", r"dec_norm\.(weight|bias)",
    r"decoder_embed\.(weight|bias)",
    r"enc_blocks\.\d+\.(norm1|norm2)\.(weight|bias)", r"enc_blocks\.\d+\.attn\.(qkv|proj)\.(weight|bias)",
    r"enc_blocks\.\d+\.mlp\.(fc1|fc2)\.(weight|bias)",
    r"dec_blocks2?\.\d+\.(norm1|norm2|norm3|norm_y)\.(weight|bias)", r"dec_blocks2?\.\d+\.attn\.(qkv|proj)\.(weight|bias)",
    r"dec_blocks2?\.\d+\.cross_attn\.(projq|projk|projv|proj)\.(weight|bias)",
    r"dec_blocks2?\.\d+\.mlp\.(fc1|fc2)\.(weight|bias)",
    r"downstream_head[12]\.dpt\.act_postprocess\.[0-3]\.[01]\.(weight|bias)",
    r"downstream_head[12]\.dpt\.scratch\.layer[1-4]_rn\.weight", r"downstream_head[12]\.dpt\.scratch\.layer_rn\.[0-3]\.weight",
    r"downstream_head[12]\.dpt\.scratch\.refinenet[1-4]\.out_conv\.(weight|bias)",
    r"downstream_head[12]\.dpt\.scratch\.refinenet[1-4]\.resConfUnit[12]\.conv[12]\.(weight|bias)",
    r"downstream_head[12]\.dpt\.head\.[024]\.(weight|bias)",
    r"downstream_head[12]\.head_local_features\.(fc1|fc2)\.(weight|bias)",
]


def test_state_dict_keys_follow_the_official_layout():
    keys = list(tiny_net().state_dict())
    unmatched = [k for k in keys if not any(re.fullmatch(p, k) for p in OFFICIAL_KEYS)]
    assert not unmatched
    for p in OFFICIAL_KEYS:  # and every kind of official parameter exists
        assert any(re.fullmatch(p, k) for k in keys), p
    assert sum(k.startswith("enc_blocks.") for k in keys) == 2 * 12
    assert sum(k.startswith("dec_blocks2.") for k in keys) == 4 * 24
    assert sum(k.startswith("downstream_head1.") for k in keys) == 14 + 8 + 4 * 10 + 6 + 4


def test_full_size_shapes_match_the_released_model():
    with torch.device("meta"):  # the 0.7 G-parameter model, without allocating it
        sd = Mast3rNet(Mast3rConfig()).state_dict()
    expect = {
        "patch_embed.proj.weight": (1024, 3, 16, 16), "enc_blocks.23.attn.qkv.weight": (3072, 1024),
        "mask_token": (1, 1, 768), "decoder_embed.weight": (768, 1024), "dec_blocks2.11.cross_attn.projk.weight": (768, 768),
        "downstream_head1.dpt.act_postprocess.0.0.weight": (96, 1024, 1, 1),
        "downstream_head1.dpt.act_postprocess.3.1.weight": (768, 768, 3, 3),
        "downstream_head2.dpt.scratch.layer4_rn.weight": (256, 768, 3, 3),
        "downstream_head2.dpt.head.4.weight": (4, 128, 1, 1),
        "downstream_head1.head_local_features.fc1.weight": (7168, 1792),
        "downstream_head1.head_local_features.fc2.weight": ((24 + 1) * 256, 7168),
    }
    for k, shape in expect.items():
        assert tuple(sd[k].shape) == shape, k
    assert "enc_blocks.24.norm1.weight" not in sd and "dec_blocks.12.norm1.weight" not in sd


def test_outputs_shapes_and_determinism():
    net = tiny_net()
    g = torch.Generator().manual_seed(1)
    x1, x2 = torch.rand(1, 3, 48, 64, generator=g) * 2 - 1, torch.rand(1, 3, 48, 64, generator=g) * 2 - 1
    with torch.no_grad():
        o1, o2 = net(x1, x2)
        again = net(x1, x2)
        other = tiny_net(0)(x1, x2)
    assert o1["pts3d"].shape == (1, 48, 64, 3) and o2["pts3d_in_other_view"].shape == (1, 48, 64, 3)
    assert o1["conf"].shape == (1, 48, 64) and bool((o1["conf"] >= 1).all())
    assert o2["desc"].shape == (1, 48, 64, 8)
    torch.testing.assert_close(o2["desc"].norm(dim=-1), torch.ones(1, 48, 64))
    for a, b in ((o1, again[0]), (o2, again[1]), (o1, other[0])):
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    # the two decoders really see each other: changing image 2 changes view 1's output
    with torch.no_grad():
        o1b, _ = net(x1, torch.flip(x2, dims=[3]))
    assert not torch.allclose(o1["pts3d"], o1b["pts3d"])


def test_encode_then_decode_equals_the_pair_at_once():
    net = tiny_net()
    g = torch.Generator().manual_seed(2)
    x1, x2 = torch.rand(1, 3, 48, 64, generator=g) * 2 - 1, torch.rand(1, 3, 48, 64, generator=g) * 2 - 1
    with torch.no_grad():
        joint = net(x1, x2)
        split = net.decode(net.encode(x1), net.encode(x2))
    for a, b in zip(joint, split):
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def views():
    cam = default_camera(96, 72)
    room = TexturedRoom(seed=0)
    Tq, Tm = look_pose((0, 0, 0)), look_pose((0.3, 0.0, 0.2), 10.0)
    return cam, room.render(Tq, cam)[0], room.render(Tm, cam)[0]


def test_registrar_split_through_bytes_matches_direct_decoding(views):
    cam, img_q, img_m = views
    reg = Mast3rRegistrar(tiny_net(), size=64, token_dtype="float32")
    eq, em = reg.encode(img_q), reg.encode(img_m)
    assert eq.arrays["tokens"].shape == (4 * 3, 32)  # 64x48 network image -> 4 x 3 patches
    eq2, em2 = Encoding.from_bytes(eq.to_bytes()), Encoding.from_bytes(em.to_bytes())
    d1, d2 = reg.decode(eq2, em2)
    xq, _ = reg.preprocess(img_q)
    xm, _ = reg.preprocess(img_m)
    with torch.no_grad():
        j1, j2 = reg.net(xq, xm)
    np.testing.assert_allclose(d1["pts3d"], j1["pts3d"][0].numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(d2["desc"], j2["desc"][0].numpy(), rtol=1e-5, atol=1e-5)
    res = reg.register(eq2, em2, cam)  # random weights: any outcome, but a PairResult, never an exception
    assert res.n_correspondences >= 0 and res.success in (True, False)
    if res.success:
        assert abs(np.linalg.norm(res.t) - 1) < 1e-9
    # float16 tokens halve the bytes on the link and change the outputs only slightly
    half = Mast3rRegistrar(reg.net, size=64)
    h1, _ = half.decode(half.encode(img_q), half.encode(img_m))
    assert half.encode(img_q).arrays["tokens"].nbytes * 2 == eq.arrays["tokens"].nbytes
    np.testing.assert_allclose(h1["pts3d"], d1["pts3d"], rtol=2e-2, atol=2e-2)


def test_checkpoint_round_trip_and_missing_checkpoint(tmp_path, views):
    net = tiny_net(3)
    path = tmp_path / "tiny_mast3r.pth"
    torch.save({"model": net.state_dict(), "args": argparse.Namespace(model=TINY_STRING)}, path)
    loaded = load_mast3r_checkpoint(path)
    assert loaded.cfg == net.cfg
    x = torch.rand(1, 3, 32, 48) * 2 - 1
    with torch.no_grad():
        for a, b in zip(net(x, x.flip(3)), loaded(x, x.flip(3))):
            for k in a:
                torch.testing.assert_close(a[k], b[k])
    with pytest.raises(InputError) as e:
        make_registrar("mast3r")
    assert "no checkpoint" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError, match="not found"):
        make_registrar("mast3r", checkpoint=str(tmp_path / "nope.pth"))
    odd = tmp_path / "odd.pth"  # a pickled object the safe loader refuses
    torch.save({"model": net.state_dict(), "args": argparse.Namespace(model=TINY_STRING, when=object.__new__(Odd))}, odd)
    with pytest.raises(InputError, match="trust_checkpoint"):
        load_mast3r_checkpoint(odd)
    assert load_mast3r_checkpoint(odd, trust_checkpoint=True).cfg == net.cfg
    other = tmp_path / "other.pth"
    torch.save({"model": {"patch_embed.proj.weight": torch.zeros(2)}}, other)
    with pytest.raises(InputError, match="does not fit"):
        load_mast3r_checkpoint(other)
    reg = make_registrar("mast3r", checkpoint=str(path), size=64)
    with pytest.raises(InputError, match="uint8"):
        reg.encode(np.zeros((64, 64, 3), np.uint16))
    with pytest.raises(InputError, match="too small"):
        reg.encode(np.zeros((8, 64, 3), np.uint8))
    cam, img_q, _ = views
    with pytest.raises(InputError, match="expects"):  # tokens of another model
        reg.register(reg.encode(img_q), Encoding("mast3r", (96, 72), {"tokens": np.zeros((12, 7), np.float16)},
                                                 reg.encode(img_q).meta), cam)


def test_fast_reciprocal_matching_recovers_a_known_shift():
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.normalize(torch.randn(40, 60, 16, generator=g), dim=-1)
    a, b = base, base[5:35, 7:50]  # b(x, y) = a(x + 7, y + 5); every pixel of b has its copy in a
    xy_a, xy_b = fast_reciprocal_nns(a, b, subsample=4)
    # pixels of a outside b hop to b and back onto a true copy, so every pair found is exact
    np.testing.assert_array_equal(xy_a - xy_b, np.tile([7, 5], (len(xy_a), 1)))
    assert len(xy_a) >= (30 // 4) * (43 // 4)  # at least every seed of b's grid converged


def test_pose_from_pointmap_matches_recovers_the_relative_pose():
    cam = default_camera(160, 120)
    room = TexturedRoom(seed=4)
    Tq, Tm = look_pose((0, 0, 0)), look_pose((0.4, -0.1, 0.3), 15.0, 4.0)
    _, depth = room.render(Tq, cam)
    pts = cam.backproject(depth)  # exact "pointmap" of view 1 in its own frame
    ys, xs = np.mgrid[4:120:6, 4:160:6].reshape(2, -1)
    xy1 = np.stack([xs, ys], 1)
    T_mq = np.linalg.inv(relative_pose(Tq, Tm))
    X = pts[ys, xs] @ T_mq[:3, :3].T + T_mq[:3, 3]
    uv, z = cam.project(X)
    ok = (z > 0) & cam.in_image(uv)
    R, t, mask, reason = pose_from_matches(pts, xy1[ok], uv[ok], cam.K)
    assert reason == "" and mask.mean() > 0.95
    np.testing.assert_allclose(R, T_mq[:3, :3], atol=1e-4)
    np.testing.assert_allclose(t, T_mq[:3, 3], atol=1e-3)
    R_fail, _, _, why = pose_from_matches(pts, xy1[:3], uv[:3], cam.K)
    assert R_fail is None and "too few" in why
