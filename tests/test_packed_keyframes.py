"""Retired keyframes are kept packed (slam.dense.packed): every read gives back the packed frame bit for bit, and an
agent that packs them tracks, maps and closes loops exactly as one that keeps them raw."""

import numpy as np
import pytest

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import RGBD
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.packed import PackedRGBD
from swarmsplat.slam.dense.submaps import Keyframe, start_submap

CAM = PinholeCamera(80.0, 80.0, 31.5, 23.5, 64, 48)


def _frame(depth: np.ndarray, seed: int = 0) -> RGBD:
    rng = np.random.default_rng(seed)
    return RGBD(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), depth, CAM)


def _same(a: RGBD, b) -> None:
    assert b.color.dtype == np.uint8 and np.array_equal(a.color, b.color)
    assert b.depth.dtype == np.float32 and np.array_equal(a.depth.view(np.uint32), b.depth.view(np.uint32))
    assert b.camera == a.camera


def test_millimetre_depth_round_trips_as_16_bit():
    rng = np.random.default_rng(1)
    mm = rng.integers(300, 65000, (48, 64)).astype(np.float32)
    mm[rng.random(mm.shape) < 0.2] = 0
    f = _frame((mm / np.float32(1000.0)).astype(np.float32))
    p = PackedRGBD(f)
    assert p._depth_mm  # one uint16 plane
    _same(f, p)


def test_any_float32_depth_round_trips_exactly():
    rng = np.random.default_rng(2)
    d = rng.uniform(0.3, 7.0, (48, 64)).astype(np.float32)  # block means of a downsampling: not millimetres
    d[rng.random(d.shape) < 0.2] = 0
    d[0, 0] = np.float32(70.0)  # beyond 65.535 m: not a uint16 of millimetres either
    f = _frame(d, seed=3)
    p = PackedRGBD(f)
    assert not p._depth_mm
    _same(f, p)
    _same(f, p.unpacked())
    assert np.array_equal(p.color_tensor().numpy(), f.color_tensor().numpy())
    assert np.array_equal(p.depth_tensor().numpy(), f.depth_tensor().numpy())
    r = p.resized(32)
    _same(f.resized(32), r)


def test_smooth_frame_packs_smaller_than_raw():
    yy, xx = np.mgrid[0:48, 0:64]
    depth = (1.0 + (xx + yy) / np.float32(1000.0)).astype(np.float32)
    color = np.stack([xx * 4, yy * 5, xx + yy], -1).astype(np.uint8)
    f = RGBD(color, depth, CAM)
    p = PackedRGBD(f)
    assert p.nbytes < (color.nbytes + depth.nbytes) / 2
    _same(f, p)


def test_start_submap_packs_the_retired_keyframes_only():
    gmap = GaussianMap()
    gmap.new_submap(np.eye(4))
    f = _frame(np.full((48, 64), 1.5, np.float32))
    old = Keyframe(0, 0, 0.0, 0, np.eye(4), f, f.resized(32))
    start_submap(gmap, np.eye(4), [old], keep_images=True, compress=True)
    new = Keyframe(1, 1, 1.0, 1, np.eye(4), f, f.resized(32))
    start_submap(gmap, np.eye(4), [old, new], keep_images=True, compress=True)
    assert isinstance(old.map_rgbd, PackedRGBD) and isinstance(old.small, PackedRGBD)
    assert isinstance(new.map_rgbd, PackedRGBD)
    _same(f, old.map_rgbd)
    _same(f.resized(32), old.small)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = generate(tmp_path_factory.mktemp("packed") / "d",
                    GeneratorConfig.preset("tiny", seed=0, agents=1, frames=16))
    return load_dataset(root).agents[0]


def test_stored_frame_reads_back_from_its_file_and_pickles_as_a_reference(tmp_path):
    import pickle

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.slam.io.submap_files import KeyframeFiles

    rng = np.random.default_rng(4)
    f = _frame(rng.uniform(0.5, 4.0, (48, 64)).astype(np.float32), seed=5)
    p = PackedRGBD(f)
    before = p.png()
    store = KeyframeFiles(tmp_path / "run" / "keyframes")
    p.store(store.small, 7)
    assert p.stored and (tmp_path / "run" / "keyframes" / "small" / "0007.bin").is_file()
    assert p.png() == before
    _same(f, p)
    _same(f, p.unpacked())
    blob = pickle.dumps(p)
    assert len(blob) < 1000  # the camera and the file's reference, not the images
    q = pickle.loads(blob)
    _same(f, q)
    # the run folder moved (a resumed run): point the store at the new place
    (tmp_path / "run").rename(tmp_path / "moved")
    with pytest.raises(InputError, match="0007.bin.*loop-closure image"):
        q.png()
    q._stored[0].folder = (tmp_path / "moved" / "keyframes" / "small").resolve()
    _same(f, q)
    (tmp_path / "moved" / "keyframes" / "small" / "0007.bin").write_bytes(b"not a keyframe at all")
    with pytest.raises(InputError, match="0007.bin: not a stored keyframe"):
        _ = q.color


def test_start_submap_moves_the_retired_keyframes_to_the_store(tmp_path):
    from swarmsplat.slam.io.submap_files import KeyframeFiles

    gmap = GaussianMap()
    gmap.new_submap(np.eye(4))
    f = _frame(np.full((48, 64), 1.5, np.float32))
    old = Keyframe(0, 0, 0.0, 0, np.eye(4), f, f.resized(32))
    store = KeyframeFiles(tmp_path / "keyframes")
    start_submap(gmap, np.eye(4), [old], keep_images=True, compress=True, frame_store=store)
    assert old.small.stored and old.map_rgbd.stored
    assert sorted(p.name for p in (tmp_path / "keyframes").rglob("*.bin")) == ["0000.bin", "0000.bin"]
    _same(f, old.map_rgbd)
    _same(f.resized(32), old.small)


def test_packed_agent_gives_the_same_poses_and_map(sequence, tmp_path):
    """Packed keyframe images, moved to files in a run folder: the same run as with raw images in memory."""
    from swarmsplat import kernels
    from swarmsplat.slam.io.submap_files import KeyframeFiles
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.dense.mapping.refine import refine_agent

    cfg = SlamConfig().override({"mapping": {"iterations": 4, "first_iterations": 10},
                                 "tracking": {"refine": False},
                                 "keyframes": {"every": 2}, "submaps": {"max_keyframes": 2},
                                 "loop_closure": {"min_index_gap": 2},
                                 "map_refine": {"max_iterations": 20}})
    kernels.use(cfg.kernels.backend, cfg.kernels.device)
    agents = []
    for compress in (False, True):
        torch_seed()
        ag = Agent(sequence.camera, cfg)
        ag.compress_keyframes = compress
        ag.frame_store = KeyframeFiles(tmp_path / "keyframes") if compress else None
        ag.keep_keyframe_images = True
        for i in range(len(sequence)):
            f = sequence[i]
            ag.step(f.index, f.timestamp, f.color, f.depth)
        refine_agent(ag, cfg.map_refine, cfg.mapping)
        agents.append(ag)
    raw, packed = agents
    assert len(packed.gmap.submaps) >= 3
    assert any(isinstance(k.small, PackedRGBD) and k.small.stored for k in packed.keyframes)
    assert not any(isinstance(k.small, PackedRGBD) for k in raw.keyframes)
    assert len(raw.loops.log) == len(packed.loops.log)
    stamps_r, T_r = raw.trajectory()
    stamps_p, T_p = packed.trajectory()
    assert np.array_equal(stamps_r, stamps_p) and np.array_equal(T_r, T_p)
    for a, b in zip(raw.keyframes, packed.keyframes):
        _same(a.small, b.small)
        _same(a.map_rgbd, b.map_rgbd)
    gr, gp = raw.gmap.merged(), packed.gmap.merged()
    for name in ("means", "log_scales", "quats", "logit_opacities", "colors"):
        assert np.array_equal(getattr(gr, name).detach().numpy(), getattr(gp, name).detach().numpy()), name


def torch_seed():
    import torch

    torch.manual_seed(0)
    np.random.seed(0)


def test_lossy_pack_keeps_full_resolution_colour():
    """Stripes one pixel wide that differ in colour, not brightness: chroma at half resolution (JPEG's usual
    4:2:0) would average them to one colour, an error of half their difference (50 in red); full-resolution
    chroma keeps them apart."""
    from swarmsplat.slam.dense.packed import pack_lossy

    color = np.empty((48, 64, 3), np.uint8)
    color[:, 0::2] = (200, 100, 100)
    color[:, 1::2] = (100, 152, 100)  # the same luma within 1
    f = RGBD(color, np.full((48, 64), 1.5, np.float32), PinholeCamera(60, 60, 32, 24, 64, 48))
    err = np.abs(pack_lossy(f, 90).color.astype(float) - color)
    assert err[..., 0].mean() < 25
