"""The synthetic multi-agent generator: format, determinism, geometry, noise model, trajectories, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.synthetic import (
    GeneratorConfig, agent_poses, cast, dataset_camera, generate, generate_world, render)
from swarmsplat.slam.synthetic.config import ColorNoiseConfig, DepthNoiseConfig, MonoConfig
from swarmsplat.slam.synthetic.mono import drifting_odometry
from swarmsplat.slam.synthetic.noise import depth_sigma, noisy_color, noisy_depth
from swarmsplat.slam.synthetic.overlap import covisibility, view_angle_deg
from swarmsplat.slam.io.trajectory import read_tum


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, GeneratorConfig]:
    cfg = GeneratorConfig.preset("tiny", seed=5)
    return generate(tmp_path_factory.mktemp("tiny") / "data", cfg), cfg


def _read_list(path: Path) -> list[tuple[float, str]]:
    rows = [line.split() for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return [(float(t), f) for t, f in rows]


def test_tiny_dataset_format(tiny):
    root, cfg = tiny
    meta = yaml.safe_load((root / "dataset.yaml").read_text())
    assert meta["name"] == cfg.name and meta["kind"] == "rgbd" and meta["seed"] == cfg.seed
    assert meta["agents"] == ["agent_0", "agent_1"]
    assert GeneratorConfig(**meta["generator"]) == cfg  # the settings round-trip
    world = generate_world(cfg.seed, cfg.world)
    camera = dataset_camera(cfg)
    for a, name in enumerate(meta["agents"]):
        folder = root / name
        calib = yaml.safe_load((folder / "calibration.yaml").read_text())
        assert set(calib) == {"fx", "fy", "cx", "cy", "width", "height", "depth_scale"}
        assert (calib["width"], calib["height"]) == (cfg.width, cfg.height)
        assert calib["cx"] == (cfg.width - 1) / 2 and calib["fx"] == pytest.approx(camera.fx)
        rgb, depth = _read_list(folder / "rgb.txt"), _read_list(folder / "depth.txt")
        assert len(rgb) == len(depth) == cfg.frames
        assert [f for _, f in rgb][:2] == ["rgb/000000.png", "rgb/000001.png"]
        stamps = np.array([t for t, _ in rgb])
        np.testing.assert_allclose(np.diff(stamps), 1 / cfg.fps, atol=2e-6)
        t_gt, T_gt = read_tum(folder / "groundtruth.txt")
        np.testing.assert_allclose(t_gt, stamps, atol=1e-6)
        np.testing.assert_allclose(T_gt, agent_poses(world, cfg)[a], atol=1e-6)
        for (_, f), (_, g) in zip(rgb, depth):
            c = cv2.imread(str(folder / f), cv2.IMREAD_UNCHANGED)
            d = cv2.imread(str(folder / g), cv2.IMREAD_UNCHANGED)
            assert c.dtype == np.uint8 and c.shape == (cfg.height, cfg.width, 3)
            assert d.dtype == np.uint16 and d.shape == (cfg.height, cfg.width)
            assert 0.005 < (d == 0).mean() < 0.3  # some holes, mostly valid
            assert c.std() > 20  # textured, not flat
    # No temporary folders are left beside the dataset.
    assert sorted(p.name for p in root.parent.iterdir()) == ["data"]


def test_folder_reader_reads_it(tiny):
    from swarmsplat.slam.io.datasets.folder import load_folder_dataset

    root, cfg = tiny
    ds = load_folder_dataset(root)
    assert len(ds) == cfg.agents and len(ds.agents[1]) == cfg.frames
    f = ds.agents[1][cfg.frames - 1]
    assert f.depth.dtype == np.float32 and 0.3 <= f.depth[f.depth > 0].min() and f.depth.max() <= 7.5


def test_identical_bytes_for_same_seed(tiny, tmp_path):
    root, cfg = tiny
    again = generate(tmp_path / "again", cfg)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (root / rel).read_bytes() == (again / rel).read_bytes(), rel
    other = generate(tmp_path / "other", cfg.model_copy(update={"seed": cfg.seed + 1, "frames": 1}))
    assert (other / "agent_0/rgb/000000.png").read_bytes() != (root / "agent_0/rgb/000000.png").read_bytes()


def test_regenerate_replaces_dataset_atomically(tiny, tmp_path):
    _, cfg = tiny
    out = generate(tmp_path / "d", cfg.model_copy(update={"frames": 2}))
    generate(out, cfg.model_copy(update={"frames": 3, "mono": True}))
    assert yaml.safe_load((out / "dataset.yaml").read_text())["kind"] == "mono"
    assert not (out / "agent_0/depth").exists() and len(list((out / "agent_0/rgb").iterdir())) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_depth_is_the_analytic_floor_and_ceiling_distance(default_world):
    world, cfg, poses = default_world
    camera = dataset_camera(cfg).scaled(80, 60)
    T = poses[0][7]
    hits = cast(world, T, camera)
    depth = hits.depth[0]
    d_world = camera.backproject(np.ones((camera.height, camera.width))) @ T[:3, :3].T  # rays with z_cam = 1
    # Where a ray hits a floor (all at z = 0), the depth must be where that ray meets the plane z = 0.
    t_floor = -T[2, 3] / np.where(d_world[..., 2] < 0, d_world[..., 2], np.nan)
    on_floor = np.isin(hits.material[0], list(_floor_materials(world)))
    assert on_floor.sum() > 0.1 * on_floor.size  # the lower part of the image is floor
    np.testing.assert_allclose(depth[on_floor], t_floor[on_floor], atol=2e-4)
    # Looking straight up from the same place, the whole centre of the image is ceiling at height - z.
    up = se3.make(np.eye(3), T[:3, 3])  # camera z (forward) = world up, x = world x, y = world y
    color, d_up = render(world, up, camera)
    centre = d_up[20:40, 30:50]
    np.testing.assert_allclose(centre, world.height - T[2, 3], atol=2e-4)
    assert color.dtype == np.uint8 and color.shape == (60, 80, 3)


def test_depth_png_holds_the_rendered_depth(tmp_path):
    cfg = GeneratorConfig.preset("tiny", frames=2, agents=1, depth_noise=DepthNoiseConfig(enabled=False),
                                 color_noise=ColorNoiseConfig(enabled=False))
    out = generate(tmp_path / "clean", cfg)
    world = generate_world(cfg.seed, cfg.world)
    T = agent_poses(world, cfg)[0][1]
    color, depth = render(world, T, dataset_camera(cfg), supersample=cfg.supersample)
    d_png = cv2.imread(str(out / "agent_0/depth/000001.png"), cv2.IMREAD_UNCHANGED) / cfg.depth_scale
    np.testing.assert_allclose(d_png, depth, atol=0.51 / cfg.depth_scale)
    c_png = cv2.imread(str(out / "agent_0/rgb/000001.png"))[..., ::-1]
    assert np.abs(c_png.astype(int) - color).max() <= 1


def test_depth_noise_statistics():
    rng = np.random.default_rng(0)
    z = np.full((300, 300), 2.5, dtype=np.float32)
    cos = np.ones_like(z)
    plain = DepthNoiseConfig(disparity_step=0.0, edge_dropout=0.0, blob_holes=0.0)
    noisy = noisy_depth(z, cos, plain, rng)
    assert noisy.mean() == pytest.approx(2.5, abs=3 * depth_sigma(2.5, plain) / 300)
    assert noisy.std() == pytest.approx(depth_sigma(2.5, plain), rel=0.05)
    assert depth_sigma(4.0, plain) > 3 * depth_sigma(1.5, plain)  # grows with range
    # Disparity quantisation: every value sits on the fb / (k * step) grid.
    quant = DepthNoiseConfig(edge_dropout=0.0, blob_holes=0.0)
    q = noisy_depth(z, cos, quant, rng)
    k = quant.disparity_fb / q / quant.disparity_step
    np.testing.assert_allclose(k, np.round(k), atol=1e-3)
    # Holes: out of range, grazing incidence, clustered blobs of the configured fraction.
    far = noisy_depth(np.full_like(z, 9.0), cos, plain, rng)
    assert (far == 0).all()
    graze = noisy_depth(z, np.full_like(z, 0.05), plain, rng)
    assert (graze == 0).all()
    blobs = noisy_depth(z, cos, DepthNoiseConfig(disparity_step=0.0, edge_dropout=0.0, blob_holes=0.05), rng)
    assert 0.02 < (blobs == 0).mean() < 0.1
    step = np.where(np.arange(300) < 150, 1.5, 3.0).astype(np.float32)[None].repeat(300, 0)
    edges = noisy_depth(step, cos, DepthNoiseConfig(edge_dropout=1.0, blob_holes=0.0), rng)
    assert (edges[:, 149:151] == 0).all() and (edges[:, 10:140] > 0).all()


def test_color_noise_statistics():
    rng = np.random.default_rng(1)
    grey = np.full((200, 200, 3), 0.5, dtype=np.float32)
    out = noisy_color(grey, ColorNoiseConfig(sigma=3.0), rng).astype(float)
    assert out.mean() == pytest.approx(127.5, abs=0.2)
    assert out.std() == pytest.approx(3.0, rel=0.06)
    assert (noisy_color(grey, ColorNoiseConfig(enabled=False), rng) == 128).all()


def test_motion_is_smooth_and_every_agent_revisits_its_start(default_world):
    world, cfg, poses = default_world
    for T in poses:
        assert T.shape == (cfg.frames, 4, 4)
        steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        rel = np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3]
        assert steps.max() <= cfg.motion.max_step_m + 1e-6
        assert np.degrees(se3.rotation_angle(rel)).max() <= cfg.motion.max_rot_deg + 1e-6
        assert steps.mean() > 0.5 * cfg.motion.max_step_m  # and it does move
        # The second half passes within 5 cm and 5 degrees of the first pose: an intra-agent revisit.
        late = T[cfg.frames // 2 :]
        near = np.linalg.norm(late[:, :3, 3] - T[0, :3, 3], axis=1) < 0.05
        angle = np.degrees(se3.rotation_angle(np.swapaxes(late[:, :3, :3], 1, 2) @ T[0, :3, :3]))
        assert (near & (angle < 5)).any()
        # Cameras stay inside the rooms, at head height, looking at surfaces 0.5 m or more away.
        assert (world.room_at(T[:, :2, 3]) >= 0).all() and (T[:, 2, 3] > 1.0).all()
    hits = cast(world, np.stack([T[::30] for T in poses]).reshape(-1, 4, 4), dataset_camera(cfg).scaled(64, 48))
    assert np.median(hits.depth) > 1.0 and np.percentile(hits.depth, 2) > 0.5


def _floor_materials(world) -> set[int]:
    """Materials of the floors' top faces (+z is face 5 of a box: triangles 10 and 11 of its 12)."""
    return {int(m) for t, m in enumerate(world.tri_material) if world.boxes[t // 12].kind == "floor" and t % 12 >= 10}


def _best_overlap(world, Ta, Tb, opposite: bool) -> float:
    best = 0.0
    for i in range(0, len(Ta), 20):
        for j in range(0, len(Tb), 20):
            angle = view_angle_deg(Ta[i], Tb[j])
            if (angle > 135) if opposite else (angle < 45):
                best = max(best, covisibility(world, Ta[i], Tb[j]))
    return best


def _same_direction_frames(world, Ta, Tb, step: int = 6) -> int:
    """How many of a's frames (every `step`-th) have a frame of b looking the same way (optical axes < 30 deg
    apart) at the same surfaces: at least half of each view's surface points seen by the other. That is what an
    inter-agent loop needs: place recognition matches similar views and registration's fitness gate (0.5)
    counts the query's points found in the match."""
    found = 0
    for i in range(0, len(Ta), step):
        for j in range(0, len(Tb), step):
            if view_angle_deg(Ta[i], Tb[j]) < 30 and min(covisibility(world, Ta[i], Tb[j]),
                                                          covisibility(world, Tb[j], Ta[i])) > 0.5:
                found += 1
                break
    return found


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_every_default_agent_has_a_same_direction_partner(seed):
    """Layout 2: in the default 3-agent dataset each agent sees some surfaces from the same place and direction
    as another agent for a stretch of frames (layout 1's agent 1 saw them only from behind and never joined)."""
    cfg = GeneratorConfig.preset("default", seed=seed)
    world = generate_world(cfg.seed, cfg.world)
    poses = agent_poses(world, cfg)
    frames = {(a, b): _same_direction_frames(world, poses[a], poses[b]) for a in range(3) for b in range(3) if a != b}
    for a in range(cfg.agents):
        best = max(n for (q, _), n in frames.items() if q == a)
        assert best >= 3, f"agent {a} has no same-direction partner: {frames}"  # >= 3 of its 20 sampled frames
    assert frames[(0, 1)] >= 3 and frames[(1, 0)] >= 3  # the designed pair: 1 walks in front of 0


def test_agents_overlap_including_from_opposite_directions(default_world):
    world, cfg, poses = default_world
    assert _best_overlap(world, poses[0], poses[3], opposite=True) > 0.1  # same place, opposite views
    assert _best_overlap(world, poses[2], poses[3], opposite=True) > 0.1
    assert _best_overlap(world, poses[0], poses[1], opposite=False) > 0.4  # same place, same direction
    assert _best_overlap(world, poses[0], poses[2], opposite=False) > 0.4
    assert _best_overlap(world, poses[4], poses[5], opposite=True) > 0.1
    # Agent k's path does not depend on how many agents there are.
    two = agent_poses(world, cfg.model_copy(update={"agents": 2}))
    np.testing.assert_array_equal(two[1], poses[1])


def test_old_layout_datasets_do_not_match_the_current_settings():
    """The layout version is part of dataset.yaml's generator settings, so a cache made with other paths is
    regenerated (demo.ensure_dataset compares those settings), and only the current layout can be asked for."""
    dump = GeneratorConfig.preset("default").model_dump(mode="json")
    assert dump["trajectory_layout"] == 2
    old = {k: v for k, v in dump.items() if k != "trajectory_layout"}  # what layout-1 datasets recorded
    assert old != dump
    with pytest.raises(InputError, match="trajectory_layout"):
        GeneratorConfig.preset("default", trajectory_layout=1)


@pytest.mark.parametrize("rooms", [(2, 1), (1, 2), (3, 2)])
def test_every_grid_keeps_cameras_in_rooms_and_clear_of_furniture(rooms):
    from swarmsplat.slam.synthetic.config import WorldConfig

    cfg = GeneratorConfig.preset("default", agents=6, seed=sum(rooms), world=WorldConfig(rooms_x=rooms[0],
                                                                                         rooms_y=rooms[1]))
    world = generate_world(cfg.seed, cfg.world)
    poses = agent_poses(world, cfg)
    for T in poses:
        p = T[:, :3, 3]
        assert (world.room_at(p[:, :2]) >= 0).all()
        for b in world.boxes:
            if b.kind == "furniture":
                assert not np.all((p > np.array(b.lo) - 0.3) & (p < np.array(b.hi) + 0.3), axis=1).any()
    hits = cast(world, np.concatenate([T[::10] for T in poses]), dataset_camera(cfg).scaled(32, 24))
    assert hits.depth.min() > 0.5 and (hits.material >= 0).all()  # a closed world: every ray hits


def test_worlds_differ_by_seed_and_rooms_differ_within_a_world():
    a, b = generate_world(0), generate_world(1)
    assert a.rooms[0].hi != b.rooms[0].hi
    floors = _floor_materials(a)
    assert len(floors) == len(a.rooms)  # each room has its own floor material, with its own colours
    assert len({tuple(np.round(a.materials.color_a[m], 3)) for m in floors}) == len(a.rooms)


def test_mono_odometry_drift():
    world = generate_world(0)
    cfg = GeneratorConfig.preset("default", frames=300)
    T = agent_poses(world, cfg)[0]
    exact = drifting_odometry(T, MonoConfig(trans_noise=0, rot_noise_deg_per_m=0, yaw_bias_deg_per_m=0),
                              np.random.default_rng(0))
    np.testing.assert_allclose(exact, se3.inverse(T[0]) @ T, atol=1e-9)
    path = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum()
    odo = drifting_odometry(T, MonoConfig(), np.random.default_rng(3))
    aligned = T[0] @ odo  # into the world frame through the first pose
    err = np.linalg.norm(aligned[-1, :3, 3] - T[-1, :3, 3])
    assert 0.001 * path < err < 0.1 * path  # drifts, but like odometry does: percent of distance travelled
    scaled = drifting_odometry(T, MonoConfig(scale=1.2, trans_noise=0, rot_noise_deg_per_m=0), np.random.default_rng(0))
    length = np.linalg.norm(np.diff(scaled[:, :3, 3], axis=0), axis=1).sum()
    assert length / path == pytest.approx(1.2, rel=1e-6)


def test_mono_dataset_files(tmp_path):
    cfg = GeneratorConfig.preset("tiny", mono=True, frames=4, agents=1)
    out = generate(tmp_path / "mono", cfg)
    folder = out / "agent_0"
    assert not (folder / "depth").exists() and not (folder / "depth.txt").exists()
    assert "depth_scale" not in yaml.safe_load((folder / "calibration.yaml").read_text())
    _, odo = read_tum(folder / "odometry.txt")
    np.testing.assert_allclose(odo[0], np.eye(4), atol=1e-9)
    _, gt = read_tum(folder / "groundtruth.txt")
    assert len(odo) == len(gt) == 4 and yaml.safe_load((out / "dataset.yaml").read_text())["kind"] == "mono"


@pytest.mark.parametrize("bad", [0, 1.5, 9, True, "2"])
def test_supersample_bad_values(bad):
    with pytest.raises(InputError, match="supersample must be an integer from 1 to 8"):
        render(generate_world(0), np.eye(4), dataset_camera(GeneratorConfig.preset("tiny")), supersample=bad)


@pytest.mark.parametrize("overrides", [dict(agents=0), dict(agents=7), dict(frames=0), dict(width=-5),
                                       dict(fps=0.0), dict(supersample=0), dict(supersample=9)])
def test_bad_settings_are_input_errors(overrides):
    with pytest.raises(InputError, match=next(iter(overrides))):
        GeneratorConfig.preset("tiny", **overrides)


def test_unknown_preset_and_bad_pose():
    with pytest.raises(InputError, match="preset"):
        GeneratorConfig.preset("huge")
    world = generate_world(0)
    cam = dataset_camera(GeneratorConfig.preset("tiny"))
    with pytest.raises(InputError):
        render(world, np.full((4, 4), math.nan), cam)
    with pytest.raises(InputError):
        render(world, np.eye(3), cam)


def test_refuses_foreign_folder_and_keeps_it(tmp_path):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    cfg = GeneratorConfig.preset("tiny", frames=1)
    with pytest.raises(InputError, match="not empty"):
        generate(foreign, cfg)
    assert (foreign / "thesis.tex").read_text() == "precious" and len(list(foreign.iterdir())) == 1
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        generate(tmp_path / "file", cfg)


def test_cli_generate_and_preview(tmp_path, capsys):
    from swarmsplat.slam.cli import main

    out, png = tmp_path / "ds", tmp_path / "world.png"
    assert main(["generate", "--preset", "tiny", "--frames", "2", "--seed", "4", "--out", str(out),
                 "--preview", str(png), "--supersample", "1"]) == 0
    meta = yaml.safe_load((out / "dataset.yaml").read_text())
    assert meta["seed"] == 4 and meta["generator"]["supersample"] == 1
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "x").write_text("x")
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "foreign")]) == 2
    assert main(["generate", "--preset", "tiny", "--agents", "9", "--out", str(tmp_path / "n")]) == 2
    assert main(["generate", "--preset", "tiny", "--supersample", "0", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "error" in err and "supersample" in err
