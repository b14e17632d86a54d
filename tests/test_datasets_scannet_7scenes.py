"""ScanNet exports and 7-Scenes sequences, rebuilt in tmp_path: detection, poses, intrinsics, depth scale and
invalid values, timestamps, the colour registered onto the depth camera, the one-line errors of an incomplete
layout, and one `swarmsplat run` on each layout (frames ray-cast from the synthetic world)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.datasets import detect_sequence_format, load_dataset, load_sequence
from swarmsplat.slam.io.datasets.sevenscenes import SEVENSCENES_CAMERA, SEVENSCENES_COLOR_CAMERA

from test_run_split import FAST_YAML

# A small ScanNet-like pair of cameras: colour larger, wider and off-centre (as ScanNet's 1296x968 iPad camera is
# to its 640x480 depth camera), so that resizing the colour without the intrinsics misplaces it.
DEPTH_CAM = PinholeCamera(36.0, 36.0, 19.5, 14.5, 40, 30)
COLOR_CAM = PinholeCamera(70.0, 70.0, 44.0, 31.0, 81, 61)


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return se3.exp(np.cumsum(rng.normal(0, 0.1, (n, 6)), axis=0))


def ray_pattern(cam: PinholeCamera, k: int) -> np.ndarray:
    """[H, W, 3] uint8 RGB that is a linear function of each pixel's ray (x/z, y/z) (so the same scene point has
    the same colour in any camera), blue marking frame k."""
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    img = np.stack([128 + 200 * x, 128 + 200 * y, np.full_like(x, 20 + 30 * k)], axis=-1)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _matrix_txt(path, M):
    np.savetxt(path, M, fmt="%f")  # what ScanNet's SensReader writes (6 decimals)


def write_scannet(root, ids=(0, 10, 20), *, depth_cam=DEPTH_CAM, color_cam=COLOR_CAM, K_depth=None, K_color=None,
                  invalid=(), seed=0):
    """ScanNet's SensReader export with `--frame_skip 10`; poses of frames in `invalid` written as -inf."""
    for d in ("color", "depth", "pose", "intrinsic"):
        (root / d).mkdir(parents=True)
    T = _poses(len(ids), seed)
    for k, i in enumerate(ids):
        cv2.imwrite(str(root / "color" / f"{i}.jpg"), cv2.cvtColor(ray_pattern(color_cam, k), cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 98])
        d = np.full((depth_cam.height, depth_cam.width), 1000 + 250 * k, np.uint16)
        d[0, 0] = 0
        cv2.imwrite(str(root / "depth" / f"{i}.png"), d)
        _matrix_txt(root / "pose" / f"{i}.txt", np.full((4, 4), -np.inf) if i in invalid else T[k])
    for name, K in (("color", color_cam.K if K_color is None else K_color),
                    ("depth", depth_cam.K if K_depth is None else K_depth)):
        M = np.eye(4)
        M[:3, :3] = K
        _matrix_txt(root / "intrinsic" / f"intrinsic_{name}.txt", M)
        _matrix_txt(root / "intrinsic" / f"extrinsic_{name}.txt", np.eye(4))
    return T


def write_sevenscenes(seq, n=3, *, seed=0, pattern=True):
    """One 7-Scenes seq-NN folder at 640x480; colour taken by the nominal Kinect RGB camera."""
    seq.mkdir(parents=True)
    T = _poses(n, seed)
    cam = SEVENSCENES_CAMERA
    for k in range(n):
        stem = seq / f"frame-{k:06d}"
        color = ray_pattern(SEVENSCENES_COLOR_CAMERA, k) if pattern else np.zeros((cam.height, cam.width, 3), np.uint8)
        cv2.imwrite(f"{stem}.color.png", cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        d = np.full((cam.height, cam.width), 1200 + 100 * k, np.uint16)
        d[0, :5] = 65535  # 7-Scenes' "no measurement"
        cv2.imwrite(f"{stem}.depth.png", d)
        np.savetxt(f"{stem}.pose.txt", T[k], fmt="%.7e", delimiter="\t")
    return T


# ---- ScanNet -------------------------------------------------------------------------------------------------

def test_scannet_export_reads_what_was_written(tmp_path):
    root = tmp_path / "scene0000_00"
    T = write_scannet(root, invalid=(10,))
    assert detect_sequence_format(root) == "scannet"
    seq = load_sequence(root)
    assert len(seq) == 3 and seq.camera == DEPTH_CAM
    np.testing.assert_allclose(seq.timestamps, [0, 10 / 30, 20 / 30])  # frame number / 30 Hz, gaps kept
    np.testing.assert_allclose(seq.gt_poses[[0, 2]], T[[0, 2]], atol=2e-6)
    assert np.isnan(seq.gt_poses[1]).all() and seq[1].T_world_cam_gt is None  # the '-inf' pose
    inner = (slice(2, -2), slice(2, -2))
    for k, f in enumerate(seq):
        assert f.depth.shape == (30, 40) and f.depth[0, 0] == 0.0
        assert f.depth[5, 5] == pytest.approx((1000 + 250 * k) / 1000.0)
        assert f.color.shape == (30, 40, 3) and f.color.dtype == np.uint8
        # every depth pixel holds the colour seen along its own ray (JPEG costs a few levels)
        err = np.abs(f.color.astype(int) - ray_pattern(DEPTH_CAM, k).astype(int))[inner]
        assert err.max() <= 4, err.max()
    naive = cv2.resize(ray_pattern(COLOR_CAM, 0), (40, 30), interpolation=cv2.INTER_AREA)
    assert np.abs(naive.astype(int) - ray_pattern(DEPTH_CAM, 0).astype(int))[inner].max() >= 10  # test can fail


def test_scannet_resized_export_scales_the_native_intrinsics(tmp_path):
    """`reader.py` with `image_size` resizes the images but writes the intrinsics of the native 1296x968 colour
    and 640x480 depth: they are scaled to the stored images."""
    K_d = PinholeCamera(577.6, 578.7, 318.9, 242.7, 640, 480)
    K_c = PinholeCamera(1170.2, 1170.2, 647.8, 483.8, 1296, 968)
    depth_cam, color_cam = K_d.scaled(40, 30), K_c.scaled(81, 61)
    write_scannet(tmp_path / "s", depth_cam=depth_cam, color_cam=color_cam, K_depth=K_d.K, K_color=K_c.K)
    seq = load_sequence(tmp_path / "s")
    assert seq.camera == pytest.approx(depth_cam)
    err = np.abs(seq[0].color.astype(int) - ray_pattern(depth_cam, 0).astype(int))[2:-2, 2:-2]
    assert err.max() <= 4


def test_scannet_without_poses_and_as_a_team(tmp_path):
    root = tmp_path / "scene0001_00"
    write_scannet(root)
    for f in (root / "pose").iterdir():
        f.unlink()
    (root / "pose").rmdir()
    ds = load_dataset(root)
    assert len(ds) == 1 and ds.meta == {"layout": "scannet"} and ds.agents[0].gt_poses is None


@pytest.mark.parametrize("breakage, message", [
    ("depth", r"scene: depth/10.png is missing \(color/10.jpg has no depth file\)$"),
    ("pose", r"scene: pose/20.txt is missing \(color/20.jpg has no pose file\)$"),
    ("intrinsic", r"scene: intrinsic/intrinsic_depth.txt is missing$"),
    ("nocolor", r"color: no colour images"),
    ("posefields", r"pose/0.txt:2: expected 4 numbers \(one row of a 4x4 matrix\), got 3$"),
    ("rotation", r"pose/0.txt:1: the 3x3 block is not a rotation matrix$"),
    ("name", r"color/first.jpg: ScanNet colour frames are named by frame number"),
    ("centre", r"intrinsic_depth.txt: principal point \(90, 14.5\) is far from the centre of the 40x30 images"),
    ("size", r"color/10.jpg: colour image is 40x30, expected 81x61 \(the size of color/0.jpg\)$"),
])
def test_scannet_incomplete_or_bad_export_names_the_file(tmp_path, breakage, message):
    root = tmp_path / "scene"
    write_scannet(root)
    if breakage == "depth":
        (root / "depth" / "10.png").unlink()
    elif breakage == "pose":
        (root / "pose" / "20.txt").unlink()
    elif breakage == "intrinsic":
        (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    elif breakage == "nocolor":
        for f in (root / "color").iterdir():
            f.unlink()
    elif breakage == "posefields":
        lines = (root / "pose" / "0.txt").read_text().splitlines()
        lines[1] = " ".join(lines[1].split()[:3])
        (root / "pose" / "0.txt").write_text("\n".join(lines) + "\n")
    elif breakage == "rotation":
        _matrix_txt(root / "pose" / "0.txt", np.diag([2.0, 1, 1, 1]))
    elif breakage == "name":
        cv2.imwrite(str(root / "color" / "first.jpg"), np.zeros((61, 81, 3), np.uint8))
    elif breakage == "centre":
        K = DEPTH_CAM.K
        K[0, 2] = 90.0
        M = np.eye(4)
        M[:3, :3] = K
        _matrix_txt(root / "intrinsic" / "intrinsic_depth.txt", M)
    elif breakage == "size":
        cv2.imwrite(str(root / "color" / "10.jpg"), np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(InputError, match=message) as e:
        seq = load_dataset(root).agents[0]
        for f in seq:
            pass
    assert "\n" not in str(e.value)


# ---- 7-Scenes ------------------------------------------------------------------------------------------------

def test_sevenscenes_sequence_and_scene(tmp_path):
    scene = tmp_path / "chess"
    T = write_sevenscenes(scene / "seq-01", n=3)
    write_sevenscenes(scene / "seq-02", n=2, seed=1)
    (scene / "TrainSplit.txt").write_text("sequence1\n")
    assert detect_sequence_format(scene / "seq-01") == "7scenes" and detect_sequence_format(scene) is None
    seq = load_sequence(scene / "seq-01")
    assert seq.camera == PinholeCamera(585.0, 585.0, 320.0, 240.0, 640, 480)
    np.testing.assert_allclose(seq.timestamps, np.arange(3) / 30.0)
    np.testing.assert_allclose(seq.gt_poses, T, atol=1e-6)
    for k, f in enumerate(seq):
        assert f.depth.dtype == np.float32 and (f.depth[0, :5] == 0).all()  # 65535 -> invalid
        assert f.depth[1, 1] == pytest.approx((1200 + 100 * k) / 1000.0)
        np.testing.assert_allclose(f.T_world_cam_gt, T[k], atol=1e-6)
        # colour taken at 525 px resampled onto the 585 px depth camera: each pixel has its own ray's colour
        err = np.abs(f.color.astype(int) - ray_pattern(SEVENSCENES_CAMERA, k).astype(int))
        assert err.max() <= 1, err.max()
    raw = load_sequence(scene / "seq-01", color_camera=None)[0].color  # the common practice: colour as recorded
    np.testing.assert_array_equal(raw, ray_pattern(SEVENSCENES_COLOR_CAMERA, 0))
    assert np.abs(raw.astype(int) - ray_pattern(SEVENSCENES_CAMERA, 0).astype(int)).max() >= 10
    ds = load_dataset(scene)
    assert [a.name for a in ds.agents] == ["seq-01", "seq-02"] and ds.meta == {"layout": "7scenes"}
    assert ds.kind == "rgbd" and [len(a) for a in ds.agents] == [3, 2]


@pytest.mark.parametrize("breakage, message", [
    ("depth", r"seq-01: frame-000001.depth.png is missing \(frame-000001.color.png has no depth file\)$"),
    ("pose", r"seq-01: frame-000002.pose.txt is missing \(frame-000002.color.png has no pose file\)$"),
    ("posetext", r"frame-000000.pose.txt:3: not a number in"),
    ("size", r"frame-000001.depth.png: image is 320x240, calibration says 640x480$"),
    ("colorsize", r"frame-000002.color.png: colour image is 320x240, expected 640x480 \(the colour camera's size\)$"),
])
def test_sevenscenes_incomplete_sequence_names_the_file(tmp_path, breakage, message):
    seq = tmp_path / "seq-01"
    write_sevenscenes(seq, n=3, pattern=False)
    if breakage == "depth":
        (seq / "frame-000001.depth.png").unlink()
    elif breakage == "pose":
        (seq / "frame-000002.pose.txt").unlink()
    elif breakage == "posetext":
        lines = (seq / "frame-000000.pose.txt").read_text().splitlines()
        lines[2] = "1 0 x 0"
        (seq / "frame-000000.pose.txt").write_text("\n".join(lines) + "\n")
    elif breakage == "size":
        cv2.imwrite(str(seq / "frame-000001.depth.png"), np.zeros((240, 320), np.uint16))
    elif breakage == "colorsize":
        cv2.imwrite(str(seq / "frame-000002.color.png"), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(InputError, match=message) as e:
        for f in load_dataset(seq).agents[0]:
            pass
    assert "\n" not in str(e.value)


def test_sevenscenes_without_poses(tmp_path):
    seq = tmp_path / "seq-03"
    write_sevenscenes(seq, n=2, pattern=False)
    for f in seq.glob("*.pose.txt"):
        f.unlink()
    s = load_sequence(seq)
    assert s.gt_poses is None and s[1].T_world_cam_gt is None


# ---- `swarmsplat run` on each layout ---------------------------------------------------------------------------

RUN_FRAMES = 4
# test_run_split's fast settings, on frames downsampled to 160 px wide.
RUN_YAML = FAST_YAML + "image: {max_width: 160}\n"
# Measured (noise-free frames): ATE 0.08 mm (ScanNet) and 0.06 mm (7-Scenes); with the colour resized instead of
# registered onto the depth camera 1.3 mm on both, so this bound also catches a missing registration.
RUN_ATE_BOUND_M = 5e-4


@pytest.fixture(scope="module")
def world_path():
    """The synthetic world and the first frames (about 3 cm apart) of one agent's path through it, T_world_cam."""
    from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, generate_world

    cfg = GeneratorConfig.preset("default")
    world = generate_world(cfg.seed, cfg.world)
    return world, agent_poses(world, cfg)[0][:RUN_FRAMES]


def _run(tmp_path, data, capsys):
    from swarmsplat.slam.cli import main

    cfg = tmp_path / "fast.yaml"
    cfg.write_text(RUN_YAML)
    out = tmp_path / "run"
    assert main(["run", str(data), "--out", str(out), "--config", str(cfg), "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["frames"] == RUN_FRAMES and (out / "trajectory.txt").is_file()
    return printed


def test_run_on_a_scannet_export(tmp_path, world_path, capsys):
    from swarmsplat.slam.synthetic import render

    world, T = world_path
    depth_cam = PinholeCamera(140.0, 140.0, 79.5, 59.5, 160, 120)
    color_cam = PinholeCamera(250.0, 250.0, 163.0, 119.0, 324, 242)  # wider and off-centre, as in ScanNet
    root = tmp_path / "scene0002_00"
    write_scannet(root, ids=range(RUN_FRAMES), depth_cam=depth_cam, color_cam=color_cam)
    for k in range(RUN_FRAMES):
        color = render(world, T[k], color_cam)[0]
        cv2.imwrite(str(root / "color" / f"{k}.jpg"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        depth = np.rint(render(world, T[k], depth_cam)[1] * 1000).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / f"{k}.png"), depth)
        _matrix_txt(root / "pose" / f"{k}.txt", T[k])
    agent = _run(tmp_path, root, capsys)
    assert agent["ate_rmse"] < RUN_ATE_BOUND_M, agent


def test_run_on_a_sevenscenes_sequence(tmp_path, world_path, capsys):
    from swarmsplat.slam.synthetic import render

    world, T = world_path
    seq = tmp_path / "seq-01"
    seq.mkdir()
    for k in range(RUN_FRAMES):
        stem = seq / f"frame-{k:06d}"
        color = render(world, T[k], SEVENSCENES_COLOR_CAMERA)[0]
        depth = np.rint(render(world, T[k], SEVENSCENES_CAMERA)[1] * 1000).astype(np.uint16)
        depth[:, :8] = 65535  # a band without measurements
        cv2.imwrite(f"{stem}.color.png", cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(f"{stem}.depth.png", depth)
        np.savetxt(f"{stem}.pose.txt", T[k], fmt="%.7e", delimiter="\t")
    agent = _run(tmp_path, seq, capsys)
    assert agent["ate_rmse"] < RUN_ATE_BOUND_M, agent
