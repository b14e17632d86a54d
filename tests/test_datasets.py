"""Loaders for our folder format and the public layouts, trajectory file readers, and their bad-input errors.

Public layouts are rebuilt in tmp_path at tiny sizes (Replica, EuRoC, KITTI); Redwood and a real TUM frame come
from ../shared/data and skip when absent.
"""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
import yaml

from conftest import shared_data
from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.datasets import MultiAgentDataset, detect_sequence_format, load_dataset, load_sequence
from swarmsplat.slam.io.trajectory import read_euroc_csv, read_kitti, read_redwood_log, read_trajectory, write_tum

W, H = 8, 6


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return se3.exp(np.cumsum(rng.normal(0, 0.1, (n, 6)), axis=0))


def _rgb(k):
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 10 * k + 1  # red channel marks the frame, to catch BGR/RGB swaps and frame mix-ups
    img[..., 1] = 7
    img[..., 2] = 200
    return img


def _depth_u16(k):
    d = np.full((H, W), 1000 + 100 * k, np.uint16)
    d[0, 0] = 0  # a hole
    return d


def write_folder(root, n=3, *, mono=False, scale=1000.0, fps=10.0, seed=0):
    """Our format, as the generator writes it."""
    (root / "rgb").mkdir(parents=True)
    t = 100.0 + np.arange(n) / fps
    lines = ["# color images", "# timestamp filename"]
    for k in range(n):
        cv2.imwrite(str(root / "rgb" / f"{k:06d}.png"), cv2.cvtColor(_rgb(k), cv2.COLOR_RGB2BGR))
        lines.append(f"{t[k]:.6f} rgb/{k:06d}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    calib = dict(fx=5.0, fy=5.0, cx=3.5, cy=2.5, width=W, height=H)
    T = _poses(n, seed)
    write_tum(root / "groundtruth.txt", t, T)
    if mono:
        write_tum(root / "odometry.txt", t, T @ se3.exp(np.array([0, 0, 0.01, 0.02, 0, 0]))[None])
    else:
        (root / "depth").mkdir()
        dl = ["# depth maps"]
        for k in range(n):
            cv2.imwrite(str(root / "depth" / f"{k:06d}.png"), _depth_u16(k))
            dl.append(f"{t[k]:.6f} depth/{k:06d}.png")
        (root / "depth.txt").write_text("\n".join(dl) + "\n")
        calib["depth_scale"] = scale
    (root / "calibration.yaml").write_text(yaml.safe_dump(calib))
    return t, T


# ---- our folder format ---------------------------------------------------------------------------------------

def test_folder_rgbd_sequence_reads_exactly_what_was_written(tmp_path):
    t, T = write_folder(tmp_path / "agent0", n=3, scale=1000.0)
    seq = load_sequence(tmp_path / "agent0")
    assert detect_sequence_format(tmp_path / "agent0") == "folder"
    assert len(seq) == 3 and seq.camera.fx == 5.0 and (seq.camera.width, seq.camera.height) == (W, H)
    np.testing.assert_allclose(seq.timestamps, t)
    np.testing.assert_allclose(seq.gt_poses, T, atol=1e-8)
    for k, f in enumerate(seq):
        assert f.index == k and f.timestamp == pytest.approx(t[k])
        assert f.color.dtype == np.uint8 and f.color.shape == (H, W, 3)
        np.testing.assert_array_equal(f.color, _rgb(k))
        assert f.depth.dtype == np.float32 and f.depth.shape == (H, W)
        assert f.depth[0, 0] == 0.0 and f.depth[1, 1] == pytest.approx((1000 + 100 * k) / 1000.0)
        np.testing.assert_allclose(f.T_world_cam_gt, T[k], atol=1e-8)
        assert f.T_world_cam_odom is None
    assert seq[-1].index == 2
    with pytest.raises(IndexError):
        seq[3]


def test_folder_loads_lazily(tmp_path):
    write_folder(tmp_path / "a", n=3)
    seq = load_sequence(tmp_path / "a")
    (tmp_path / "a" / "depth" / "000001.png").unlink()  # after loading the index: only frame 1 breaks
    assert seq[0].depth is not None and seq[2].depth is not None
    with pytest.raises(InputError, match="000001.png"):
        seq[1]


def test_folder_monocular_sequence(tmp_path):
    t, T = write_folder(tmp_path / "m", n=4, mono=True)
    seq = load_sequence(tmp_path / "m")
    assert not seq.is_rgbd and seq[0].depth is None
    assert seq.odometry.shape == (4, 4, 4) and seq[2].T_world_cam_odom is not None
    np.testing.assert_allclose(seq.gt_poses, T, atol=1e-8)


def test_multi_agent_dataset_yaml_with_extra_keys(tmp_path):
    for k, a in enumerate(["robot_b", "robot_a"]):
        write_folder(tmp_path / a, n=2 + k, seed=k)
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump(
        {"name": "two", "kind": "rgbd", "agents": ["robot_b", "robot_a"], "seed": 7, "generator": {"fps": 10}}))
    ds = load_dataset(tmp_path)
    assert isinstance(ds, MultiAgentDataset) and len(ds) == 2
    assert [s.name for s in ds.agents] == ["robot_b", "robot_a"]  # the order dataset.yaml gives
    assert [len(s) for s in ds.agents] == [2, 3]
    assert ds.name == "two" and ds.kind == "rgbd" and ds.meta == {"seed": 7, "generator": {"fps": 10}}


def test_single_sequence_becomes_one_agent_dataset(tmp_path):
    write_folder(tmp_path / "solo", n=2)
    ds = load_dataset(tmp_path / "solo")
    assert len(ds) == 1 and ds.agents[0].name == "solo" and ds.kind == "rgbd"


@pytest.mark.parametrize(
    "breakage, message",
    [
        ("count", "rgb.txt lists 3 frames but depth.txt lists 2"),
        ("depth8", "000001.png: depth image must be 16-bit"),
        ("depthrgb", "000001.png: depth image must have one channel"),
        ("listline", "rgb.txt:6: expected 'timestamp relative/path'"),
        ("calib", "missing key(s) depth_scale"),
        ("gtnan", "groundtruth.txt:3: NaN"),
        ("size", "calibration says 8x6"),
        ("longname", "rgb.txt:6: file name cannot be used: File name too long"),
    ],
)
def test_folder_bad_input_names_the_file(tmp_path, breakage, message):
    root = tmp_path / "bad"
    write_folder(root, n=3)
    if breakage == "count":
        lines = (root / "depth.txt").read_text().splitlines()
        (root / "depth.txt").write_text("\n".join(lines[:-1]) + "\n")
    elif breakage == "depth8":
        cv2.imwrite(str(root / "depth" / "000001.png"), np.full((H, W), 9, np.uint8))
    elif breakage == "depthrgb":
        cv2.imwrite(str(root / "depth" / "000001.png"), np.full((H, W, 3), 900, np.uint16))
    elif breakage == "listline":
        with open(root / "rgb.txt", "a") as f:
            f.write("101.5 rgb/000001.png extra\n")
    elif breakage == "calib":
        c = yaml.safe_load((root / "calibration.yaml").read_text())
        del c["depth_scale"]
        (root / "calibration.yaml").write_text(yaml.safe_dump(c))
    elif breakage == "gtnan":
        lines = (root / "groundtruth.txt").read_text().splitlines()
        lines[2] = lines[2].split()[0] + " nan 0 0 0 0 0 1"
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    elif breakage == "size":
        cv2.imwrite(str(root / "rgb" / "000001.png"), np.zeros((H + 1, W, 3), np.uint8))
    elif breakage == "longname":  # longer than any file system's name limit (255 bytes on Linux, macOS, Windows)
        with open(root / "rgb.txt", "a") as f:
            f.write(f"101.5 rgb/{'x' * 300}.png\n")
    with pytest.raises(InputError) as e:
        seq = load_sequence(root)
        for f in seq:
            pass
    assert message in str(e.value)


def test_missing_and_unknown_inputs(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(InputError, match="unknown dataset format 'kinect'"):
        load_sequence(tmp_path, fmt="kinect")
    with pytest.raises(InputError, match="not a recognised sequence"):
        load_sequence(tmp_path)
    write_folder(tmp_path / "a", n=2)
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump({"name": "x", "kind": "mono", "agents": ["a"]}))
    with pytest.raises(InputError, match="kind 'mono'"):
        load_dataset(tmp_path)
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump({"name": "x", "kind": "rgbd", "agents": ["a", "b"]}))
    with pytest.raises(InputError, match="agent folder not found"):
        load_dataset(tmp_path)
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump({"name": "x", "kind": "rgbd", "agents": ["a", "b" * 300]}))
    with pytest.raises(InputError, match="dataset.yaml: agents: folder name cannot be used"):
        load_dataset(tmp_path)
    with pytest.raises(InputError, match="dataset path: file name cannot be used"):
        load_dataset(tmp_path / ("c" * 300))


# ---- TUM RGB-D -----------------------------------------------------------------------------------------------

def test_tum_layout_with_a_real_kinect_frame(tmp_path):
    src = shared_data("tum_single_frame")
    root = tmp_path / "rgbd_dataset_freiburg1_test"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    shutil.copy(src / "TUM_color.png", root / "rgb" / "1.000000.png")
    shutil.copy(src / "TUM_color.png", root / "rgb" / "1.500000.png")  # no depth partner: dropped
    shutil.copy(src / "TUM_depth.png", root / "depth" / "1.010000.png")
    (root / "rgb.txt").write_text("# color images\n1.000000 rgb/1.000000.png\n1.500000 rgb/1.500000.png\n")
    (root / "depth.txt").write_text("# depth maps\n1.010000 depth/1.010000.png\n")
    write_tum(root / "groundtruth.txt", np.array([0.97, 1.004]), _poses(2))
    seq = load_sequence(root)
    assert detect_sequence_format(root) == "tum"
    assert len(seq) == 1 and seq.camera.fx == pytest.approx(517.3)  # freiburg1 intrinsics from the name
    f = seq[0]
    raw = cv2.imread(str(src / "TUM_depth.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(f.depth, raw.astype(np.float32) / 5000.0)
    assert f.color.shape == (480, 640, 3)
    np.testing.assert_array_equal(f.color, cv2.imread(str(src / "TUM_color.png"))[..., ::-1])
    assert 0.3 < np.median(f.depth[f.depth > 0]) < 6.0  # a room seen by a Kinect, in metres
    np.testing.assert_allclose(f.T_world_cam_gt, _poses(2)[1], atol=1e-8)  # nearest GT sample (4 ms away)


# ---- Redwood / ICL-NUIM --------------------------------------------------------------------------------------

def test_redwood_livingroom_sample():
    root = shared_data("redwood_livingroom1_rgbd5")
    seq = load_sequence(root)
    assert detect_sequence_format(root) == "redwood"
    assert len(seq) == 5
    cam = seq.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (525.0, 525.0, 319.5, 239.5, 640, 480)
    f = seq[2]
    valid = f.depth > 0
    assert 0.8 < valid.mean() < 0.95  # the noisy variant: ~87% valid per PROVENANCE
    assert 0.5 < np.median(f.depth[valid]) < 6.0  # millimetres / 1000 -> metres
    # Ground truth: the .log matrices, read independently.
    rows = [l.split() for l in (root / "trajectory.log").read_text().splitlines() if l.strip()]
    mats = np.array([[float(v) for v in r] for k, r in enumerate(rows) if k % 5]).reshape(-1, 4, 4)
    np.testing.assert_allclose(seq.gt_poses, mats)
    np.testing.assert_allclose(f.T_world_cam_gt, mats[2])
    np.testing.assert_allclose(seq.odometry[0][:3, 3], [2.0, 2.0, -0.3])  # PROVENANCE: odometry offset


# ---- Replica / Multiagent Replica ----------------------------------------------------------------------------

def write_replica(root, n=3, extra_poses=0, seed=0):
    (root / "results").mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(root / "results" / f"frame{k:06d}.jpg"), cv2.cvtColor(_rgb(k), cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
        cv2.imwrite(str(root / "results" / f"depth{k:06d}.png"), np.full((H, W), 6553, np.uint16))
    T = _poses(n + extra_poses, seed)
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.17g}" for v in P.ravel()) + "\n" for P in T))
    return T


def test_replica_sequence_and_multiagent(tmp_path):
    scene = tmp_path / "Apart-0"
    T0 = write_replica(scene / "part1", n=3, extra_poses=2)  # CP-SLAM's extra poses are dropped
    write_replica(scene / "part2", n=2, seed=1)
    (scene / "cam_params.json").write_text('{"camera": {"w": 8, "h": 6, "fx": 4.0, "fy": 4.0, "cx": 3.5, "cy": 2.5, "scale": 6553.5}}')
    seq = load_sequence(scene / "part1")
    assert detect_sequence_format(scene / "part1") == "replica"
    assert len(seq) == 3 and seq.camera.fx == 4.0
    np.testing.assert_allclose(seq.gt_poses, T0[:3])
    f = seq[1]
    assert np.abs(f.color.astype(int) - _rgb(1)).max() <= 3  # JPEG
    assert f.depth[0, 0] == pytest.approx(6553 / 6553.5)
    ds = load_dataset(scene)
    assert [s.name for s in ds.agents] == ["part1", "part2"] and ds.kind == "rgbd"
    (scene / "part2" / "traj.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="1 poses for 2 frames"):
        load_dataset(scene)


# ---- EuRoC ---------------------------------------------------------------------------------------------------

T_BS = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
                 [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
                 [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
                 [0.0, 0.0, 0.0, 1.0]])


def write_euroc(root, n=4, dist=(0.0, 0.0, 0.0, 0.0)):
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    t_ns = 1403636579763555584 + np.arange(n, dtype=np.int64) * 50_000_000
    rows = ["#timestamp [ns],filename"]
    rng = np.random.default_rng(0)
    for k, t in enumerate(t_ns):
        cv2.imwrite(str(cam / "data" / f"{t}.png"), rng.integers(0, 255, (H, W), dtype=np.uint8))
        rows.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(rows) + "\n")
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{', '.join(repr(float(v)) for v in T_BS.ravel())}]\n"
        f"rate_hz: 20\nresolution: [{W}, {H}]\ncamera_model: pinhole\nintrinsics: [4.5, 4.6, 3.4, 2.6]\n"
        f"distortion_model: radial-tangential\ndistortion_coefficients: [{', '.join(map(str, dist))}]\n")
    # Ground truth at 200 Hz, starting after the first image (as real EuRoC recordings do).
    g_ns = np.arange(t_ns[0] + 20_000_000, t_ns[-1] + 10_000_000, 5_000_000, dtype=np.int64)
    Tb = _poses(len(g_ns), 3)
    xyz, q = se3.to_tum(Tb)
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x, b_w_RS_S_y, b_w_RS_S_z, "
             "b_a_RS_S_x, b_a_RS_S_y, b_a_RS_S_z"]
    for t, p, qq in zip(g_ns, xyz, q):
        lines.append(",".join([str(t)] + [repr(float(v)) for v in (*p, qq[3], qq[0], qq[1], qq[2])] + ["0.0"] * 9))
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    return t_ns, g_ns, Tb


def test_euroc_monocular_with_extrinsic(tmp_path):
    t_ns, g_ns, Tb = write_euroc(tmp_path / "MH_01_easy")
    seq = load_sequence(tmp_path / "MH_01_easy")
    assert detect_sequence_format(tmp_path / "MH_01_easy") == "euroc"
    assert len(seq) == 4 and not seq.is_rgbd and seq.camera.fx == 4.5
    np.testing.assert_allclose(seq.timestamps, t_ns * 1e-9)
    assert np.isnan(seq.gt_poses[0]).all() and seq[0].T_world_cam_gt is None  # before motion capture starts
    for k in range(1, 4):  # image k at +50k ms: GT sample index (50k - 20) / 5
        j = (50 * k - 20) // 5
        np.testing.assert_allclose(seq.gt_poses[k], Tb[j] @ T_BS, atol=1e-9)
    f = seq[1]
    assert f.color.shape == (H, W, 3) and (f.color[..., 0] == f.color[..., 2]).all()  # grey replicated
    raw = cv2.imread(str(seq.color_paths[1]), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(f.color[..., 0], raw)  # zero distortion: no remap


def test_euroc_undistorts_when_distorted(tmp_path):
    write_euroc(tmp_path / "V1", dist=(-0.28, 0.07, 0.0002, 0.00002))
    a = load_sequence(tmp_path / "V1")[1].color
    b = load_sequence(tmp_path / "V1", undistort=False)[1].color
    assert a.shape == b.shape and not np.array_equal(a, b)


def test_euroc_collection_is_a_mono_team(tmp_path):
    write_euroc(tmp_path / "MH_01")
    write_euroc(tmp_path / "MH_02")
    ds = load_dataset(tmp_path)
    assert ds.kind == "mono" and [s.name for s in ds.agents] == ["MH_01", "MH_02"]


# ---- trajectory files ----------------------------------------------------------------------------------------

def test_kitti_reader_and_errors(tmp_path):
    T = _poses(5)
    p = tmp_path / "poses.txt"
    p.write_text("".join(" ".join(f"{v:.17g}" for v in P[:3].ravel()) + "\n" for P in T))
    t, R = read_kitti(p)
    np.testing.assert_allclose(R, T)
    np.testing.assert_array_equal(t, np.arange(5))
    tr = read_trajectory(p)
    assert tr.fmt == "kitti" and not tr.stamped
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    np.testing.assert_allclose(np.stack(evo_fi.read_kitti_poses_file(str(p)).poses_se3), R)
    p.write_text(p.read_text() + "1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="poses.txt:6: expected 12 numbers"):
        read_kitti(p)
    p.write_text("2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match="poses.txt:1: .*not a rotation"):
        read_kitti(p)


def test_euroc_csv_reader_matches_evo(tmp_path):
    write_euroc(tmp_path / "s")
    f = tmp_path / "s" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    t, T = read_euroc_csv(f)
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    ref = evo_fi.read_euroc_csv_trajectory(str(f))
    np.testing.assert_allclose(t, ref.timestamps)
    np.testing.assert_allclose(T, np.stack(ref.poses_se3), atol=1e-12)
    assert read_trajectory(f).fmt == "euroc"


def test_redwood_log_reader_and_errors(tmp_path):
    p = tmp_path / "t.log"
    T = _poses(2)
    p.write_text("".join(f"{k} {k} {k + 1}\n" + "\n".join(" ".join(f"{v:.17g}" for v in r) for r in P) + "\n"
                         for k, P in enumerate(T)))
    ids, R = read_redwood_log(p)
    np.testing.assert_allclose(R, T)
    p.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n")
    with pytest.raises(InputError, match="ends mid-entry"):
        read_redwood_log(p)


def test_unknown_trajectory_format(tmp_path):
    with pytest.raises(InputError, match="unknown trajectory format 'g2o'"):
        read_trajectory(tmp_path / "x.txt", "g2o")
