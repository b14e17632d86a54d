"""The compact form of a finished submap (slam.dense.submap_codec) and finished submaps kept off the heap
(GaussianMap.retire, slam.io.submap_files): round trips within half a quantisation step, renders within the
rasteriser's bounds, clear errors on foreign or corrupt bytes, and a stored submap that pickles as its file."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.dense.gaussian_map import GaussianMap, GaussianParams
from swarmsplat.slam.dense.submap_codec import (
    EXACT, CodecError, CodecSpec, MemoryStore, decode, encode, error_bounds, use_storage,
)
from swarmsplat.slam.io.submap_files import SubmapFiles

pytestmark = pytest.mark.usefixtures("one_torch_thread")

F32 = float(np.finfo(np.float32).eps)
SPECS = [CodecSpec(), CodecSpec(16, 16, 16, 16), CodecSpec(compression="lzma"), CodecSpec(compression="none"),
         CodecSpec(scale_bits=16, color_bits=16)]


def random_params(n: int, seed: int = 0) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    p = GaussianParams(torch.randn(n, 3, generator=g) * 2.0 + 1.0, torch.randn(n, 3, generator=g) * 0.5 - 4.0,
                       torch.randn(n, 4, generator=g), torch.randn(n, generator=g) * 3.0,
                       torch.rand(n, 3, generator=g) * 1.4 - 0.2)  # colours outside [0, 1] too
    if n:
        p.logit_opacities[0] = 30.0  # opacity 1 in float32
        p.logit_opacities[-1] = -30.0
    return p


def unit_quats(q: torch.Tensor) -> np.ndarray:
    q = q.double() / q.double().norm(dim=1, keepdim=True)
    return torch.where(q[:, :1] < 0, -q, q).numpy()


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: f"{s.bits()}-{s.compression}")
def test_round_trip_is_within_half_a_quantisation_step(spec):
    p = random_params(2000)
    d = decode(encode(p, spec))
    b = error_bounds(p, spec)
    x = lambda t: t.double().numpy()  # noqa: E731
    # half a step, plus the float32 rounding of the decoded value (a few ulps of its magnitude)
    slack = lambda a: 4 * F32 * np.abs(a).max()  # noqa: E731
    assert np.all(np.abs(x(d.means) - x(p.means)) <= b["means"] + slack(x(p.means)))
    assert np.all(np.abs(x(d.log_scales) - x(p.log_scales)) <= b["log_scales"] + slack(x(p.log_scales)))
    assert np.all(np.abs(x(d.quats) - unit_quats(p.quats)) <= b["quats"] + 4 * F32)
    o, o_hat = torch.sigmoid(p.logit_opacities.double()).numpy(), torch.sigmoid(d.logit_opacities.double()).numpy()
    # the logit is stored as float32: sigmoid moves by at most o(1 - o) x its rounding error, < 1 ulp of 1
    assert np.all(np.abs(o_hat - o) <= b["opacities"] + 4 * F32)
    assert np.all(np.abs(x(d.colors) - x(p.colors).clip(0, 1)) <= b["colors"] + 4 * F32)
    assert all(t.dtype == torch.float32 for t in d.tensors()) and torch.isfinite(d.logit_opacities).all()


def test_the_exact_form_is_bit_for_bit_and_steps_shrink_with_bits():
    p = random_params(300, seed=3)
    d = decode(encode(p, EXACT))
    assert all(torch.equal(a, b) for a, b in zip(d.tensors(), p.tensors()))
    b8, b16 = error_bounds(p, CodecSpec()), error_bounds(p, CodecSpec(16, 16, 16, 16))
    assert b16["colors"] < b8["colors"] / 200 and np.all(b8["means"] == b16["means"])


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_gaussian_submaps_round_trip(n):
    p = random_params(n)
    d = decode(encode(p))
    assert len(d) == n
    if n:  # a box of zero size: the mean comes back exactly
        assert torch.equal(d.means, p.means)


def test_compact_form_is_17_bytes_a_gaussian_before_entropy_coding():
    from swarmsplat.slam.dense.submap_codec import _HEADER

    p = random_params(5000)  # random numbers: zlib finds nothing to squeeze, and must not add more than a little
    raw = len(encode(p, CodecSpec(compression="none")))
    assert raw == _HEADER.size + 17 * len(p) and len(encode(p)) <= raw * 1.01 + 64


def test_renders_of_a_submap_before_and_after_stay_within_the_quantisation_bounds(backend):
    """A submap fitted to nothing in particular (Gaussians on a ray-cast room, tests/slam_scene.py) rendered at
    three poses. Colours move by at most half an 8-bit step (1/510), opacities by as much; means move by
    micrometres and sizes by under 2 %, which shifts footprint edges by a fraction of a pixel. So the mean
    colour and alpha change stays below 2/255, and a pixel moves by more than 16/255 only where two Gaussians
    swap depth order or a footprint edge crosses a pixel centre (bounded: under 2 % of the pixels)."""
    from swarmsplat.slam.dense.render import render, viewmat_from_pose
    import slam_scene

    cam = slam_scene.camera(64, 48)
    T0 = slam_scene.trajectory(1)[0]
    color, depth = slam_scene.render(T0, cam)
    v, u = np.mgrid[0:cam.height:2, 0:cam.width:2]
    z = depth[v, u]
    pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1).reshape(-1, 3)
    p = GaussianParams.from_points(torch.tensor(pts, dtype=torch.float32),
                                   torch.tensor(color[v, u].reshape(-1, 3) / 255.0, dtype=torch.float32),
                                   torch.tensor(z.reshape(-1) * 2.0 / cam.fx, dtype=torch.float32), opacity=0.8)
    d = decode(encode(p))
    for T in slam_scene.trajectory(9)[::4]:
        vm = viewmat_from_pose(se3.inverse(T0) @ T)
        with torch.no_grad():
            a, b = render(p, vm, cam), render(d, vm, cam)
        dc = (a.color.clamp(0, 1) - b.color.clamp(0, 1)).abs()
        assert float(dc.mean()) < 2 / 255 and float((a.alpha - b.alpha).abs().mean()) < 2 / 255
        assert float((dc.max(dim=-1).values > 16 / 255).float().mean()) < 0.02


def test_foreign_truncated_or_corrupt_bytes_name_the_source_and_what_was_expected():
    blob = encode(random_params(50))
    with pytest.raises(CodecError, match=r"x/0007\.bin: not a compact submap \(expected .*SSGC"):
        decode(b"PK\x03\x04" + blob[4:], source="x/0007.bin")
    with pytest.raises(CodecError, match=r"x\.bin: not a compact submap"):
        decode(blob[:10], source="x.bin")
    with pytest.raises(CodecError, match=r"x\.bin: corrupt compact submap \(expected a \d+-byte payload"):
        decode(blob[:-3], source="x.bin")
    flipped = bytearray(blob)
    flipped[-5] ^= 0xFF
    with pytest.raises(CodecError, match=r"x\.bin: corrupt compact submap .*CRC-32"):
        decode(bytes(flipped), source="x.bin")
    newer = bytearray(blob)
    newer[4] = 9
    with pytest.raises(CodecError, match=r"x\.bin: compact submap format version 9, this version reads 1 and 2"):
        decode(bytes(newer), source="x.bin")
    assert issubclass(CodecError, InputError)


@pytest.mark.parametrize("n", [0, 1, 3000])
def test_the_link_form_decodes_to_the_stored_values_in_morton_order(n):
    """for_link keeps every quantised value (the stored form's box and ranges), reorders along the Morton curve,
    and with `keep` sends exactly the kept Gaussians; on a smooth surface it is far smaller than the stored form."""
    from swarmsplat.slam.dense.submap_codec import LINK_VERSION, for_link

    p = random_params(n, seed=5)
    blob = encode(p)
    stored, link = decode(blob), for_link(blob)
    assert link[4] == LINK_VERSION and len(decode(link)) == n

    def rows(q):  # the Gaussians as a set of rows, whatever their order
        a = torch.cat([q.means, q.log_scales, q.quats, q.logit_opacities[:, None], q.colors], 1).numpy()
        return a[np.lexsort(a.T[::-1])]

    assert np.array_equal(rows(decode(link)), rows(stored))
    keep = np.arange(n) % 3 == 0
    assert np.array_equal(rows(decode(for_link(blob, keep))), rows(stored.select(torch.as_tensor(keep))))
    if n > 1:
        step = lambda m: np.median(np.linalg.norm(np.diff(m, axis=0), axis=1))  # noqa: E731
        assert step(decode(link).means.numpy()) < 0.25 * step(stored.means.numpy())  # neighbours along the curve
        u, v = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 50))
        z = 0.3 * np.sin(3 * u) * np.cos(2 * v)  # Gaussians seeded on a surface, as mapping seeds them
        s = GaussianParams.from_points(torch.tensor(np.stack([u, v, z], -1).reshape(-1, 3), dtype=torch.float32),
                                       torch.rand(3000, 3), torch.full((3000,), 0.01), opacity=0.9)
        surface = encode(s)
        assert len(for_link(surface)) < 0.8 * len(surface)


def test_the_link_form_with_fewer_mean_bits_stays_within_half_a_step():
    from swarmsplat.slam.dense.submap_codec import for_link

    p = random_params(2000, seed=7)
    blob = encode(p)
    stored = decode(blob).means.double().numpy()
    back = decode(for_link(blob, mean_bits=12)).means.double().numpy()
    step12, step16 = 2 * error_bounds(p, CodecSpec())["means"] / 4095 * 65535, 2 * error_bounds(p)["means"]
    # every decoded mean is within half a 12-bit step of a stored one (a nearest neighbour, any order)
    d = np.abs(back[:, None, :] - stored[None, :, :]).max(-1)  # [N, N] Chebyshev in units of metres
    assert np.all(d.min(1) <= (0.5 * step12 + 0.5 * step16).max() + 1e-6)
    assert len(for_link(blob, mean_bits=12)) < len(for_link(blob))
    with pytest.raises(InputError, match="mean_bits must be 10-16"):
        for_link(blob, mean_bits=8)


def test_the_link_form_refuses_bad_bytes_and_exact_input():
    from swarmsplat.slam.dense.submap_codec import for_link

    blob = encode(random_params(200))
    link = for_link(blob)
    with pytest.raises(CodecError, match=r"SubmapData: corrupt compact submap"):
        decode(link[:-7], source="SubmapData")
    broken = bytearray(link)
    broken[-9] ^= 0x55
    with pytest.raises(CodecError, match=r"CRC-32"):
        decode(bytes(broken))
    with pytest.raises(CodecError, match=r"the link form is made from a quantised stored form"):
        for_link(encode(random_params(10), EXACT))
    with pytest.raises(CodecError, match=r"the link form is made from a quantised stored form"):
        for_link(link)
    with pytest.raises(InputError, match=r"keep must be \[200\] bool"):
        for_link(blob, np.ones(7, bool))


def _map_with_two_submaps(store=None, storage="compact") -> GaussianMap:
    m = GaussianMap()
    use_storage(m, storage, store)
    m.add(m.new_submap(np.eye(4)), random_params(40, 1))
    s0 = m.active
    m.new_submap(se3.exp(np.array([0.0, 0.2, 0.0, 1.0, 0.0, 0.0])))
    m.retire(s0)
    m.add(m.active, random_params(30, 2))
    return m


def test_a_retired_submap_lives_in_its_file_and_pickles_as_a_reference(tmp_path):
    m = _map_with_two_submaps(SubmapFiles(tmp_path / "submaps"))
    s0 = m.submaps[0]
    assert (tmp_path / "submaps" / "0000.bin").is_file() and s0.stored is not None and s0._params is None
    assert len(s0) == 40 and len(m) == 70
    expected = decode((tmp_path / "submaps" / "0000.bin").read_bytes())
    assert torch.equal(s0.params.means, expected.means)
    assert m.nbytes() == m.submaps[1].params.nbytes()  # only the active submap's tensors are held

    blob = pickle.dumps(m)
    assert len(blob) < 8000  # no Gaussians of the stored submap inside (40 x 56 bytes would be 2 kB; the
    back = pickle.loads(blob)  # active submap's 30 are), and they come back from the file
    assert torch.equal(back.submaps[0].params.means, expected.means)
    assert back.submaps[0].stored.store.folder == (tmp_path / "submaps").resolve()

    # moving a stored submap reads nothing; reading it without its file names the file
    (tmp_path / "submaps" / "0000.bin").unlink()
    from swarmsplat.slam.dense import gaussian_map
    gaussian_map._CACHE.clear()
    GaussianMap.transform_submap(back.submaps[0], se3.exp(np.array([0.1, 0, 0, 0, 0, 0.5])))
    with pytest.raises(InputError, match=r"cannot read .*submaps/0000\.bin"):
        back.submaps[0].params  # noqa: B018 - reading the property is what raises


def test_compact_storage_without_a_folder_stays_in_memory_and_float32_keeps_tensors():
    m = _map_with_two_submaps()
    assert isinstance(m.store, MemoryStore) and 0 < m.store.nbytes() < 40 * 56
    assert m.submaps[0].stored is not None and len(m.merged()) == 70
    m32 = _map_with_two_submaps(storage="float32")
    assert m32.store is None and m32.submaps[0].stored is None
    # assigning Gaussians (the final refinement does) holds them in memory again
    m.submaps[0].params = random_params(5)
    assert m.submaps[0].stored is None and len(m) == 35


def test_a_full_disk_stops_with_one_line_naming_the_file(tmp_path, monkeypatch):
    import os

    from swarmsplat.kernels.errors import OutputError

    files = SubmapFiles(tmp_path / "s")

    def full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OutputError, match=r"cannot write .*s/0003\.bin: the disk is full \(No space left on device\)"):
        files.write(3, b"abc")
    assert not (tmp_path / "s" / "0003.bin").exists()


def test_the_link_sends_a_stored_submap_as_its_compact_bytes_and_refuses_corrupt_ones():
    from swarmsplat.slam.dense.submap_codec import _morton, _parse, _quantised, for_link
    from swarmsplat.slam.flocc.swarm.messages import MessageError
    from swarmsplat.slam.run.team_link import messages as L

    m = _map_with_two_submaps()
    s0 = m.submaps[0]
    msg = L.SubmapData.pack(5, s0, "compact")
    assert msg.blob.tobytes() == for_link(m.store.read(0))  # the stored values, not quantised again
    h, back = L.LINK.decode(L.LINK.encode(msg, 2, 9))
    order = np.argsort(_morton(_quantised(*_parse(m.store.read(0), "x"))["means"]), kind="stable")
    assert back.id == 0 and all(torch.equal(a, b[order]) for a, b in zip(back.params().tensors(),
                                                                          s0.params.tensors()))
    # a submap held as tensors (the active one) is encoded on the way out
    _, back = L.LINK.decode(L.LINK.encode(L.SubmapData.pack(6, m.active, "compact"), 2, 10))
    assert len(back.params()) == 30
    bad = L.SubmapData.pack(7, s0, "compact")
    bad.blob = bad.blob.copy()
    bad.blob[-1] ^= 0xFF
    with pytest.raises(MessageError, match="SubmapData: corrupt compact submap"):
        L.LINK.decode(L.LINK.encode(bad, 2, 11))
