"""The agent end to end: skipped frames, intra-agent loop closure against injected drift, a tiny sequence through
`run_sequence` and the `swarmsplat run` command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from swarmsplat import kernels
from swarmsplat.kernels import se3
from swarmsplat.slam.dense.agent import Agent
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.frames import make_rgbd
from swarmsplat.slam.dense.gaussian_map import GaussianMap
from swarmsplat.slam.dense.loops.loop_closure import LoopCloser
from swarmsplat.slam.dense.submaps import Keyframe, world_pose

import slam_scene

QUICK = {  # small and fast: tiny images, a handful of iterations
    "image": {"max_width": 160},
    "tracking": {"iterations": 8, "refine_max_width": 80, "pyramid_levels": 1, "coarse_max_width": 160},
    "mapping": {"max_width": 80, "iterations": 8, "first_iterations": 20, "seed_stride": 2},
    "submaps": {"keep_keyframe_width": 80},
}

@pytest.fixture(scope="module")
def warp_cpu():
    # One torch thread, as `swarmsplat run` uses: the per-call tensors are small (see KernelsConfig.torch_threads).
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield kernels.use("warp", "cpu")
    torch.set_num_threads(n)


def test_frame_without_valid_depth_is_skipped_with_a_warning(warp_cpu):
    cam = slam_scene.camera(48, 36)
    agent = Agent(cam, SlamConfig().override(QUICK))
    poses = slam_scene.trajectory(2)
    c, d = slam_scene.render(poses[0], cam)
    assert agent.step(0, 0.0, c, d) is not None
    with pytest.warns(RuntimeWarning, match="frame 1 skipped"):
        assert agent.step(1, 0.1, c, np.zeros_like(d)) is None
    with pytest.warns(RuntimeWarning, match="frame 2 skipped"):
        assert agent.step(2, 0.2, c, np.full_like(d, np.nan)) is None
    c1, d1 = slam_scene.render(poses[1], cam)
    assert agent.step(3, 0.3, c1, d1) is not None
    stamps, T = agent.trajectory()
    assert list(stamps) == [0.0, 0.3] and np.all(np.isfinite(T))
    assert agent.time.skipped == [1, 2]


def test_loop_closure_corrects_injected_drift():
    """Six keyframes in six submaps along a short path that returns to its start; tracking drift is injected as
    a growing error of the submap frames. The loop between the last and the first keyframe must be found,
    verified by registration and pull the last keyframe back."""
    cam = slam_scene.camera(160, 120)
    cfg = SlamConfig().override({"loop_closure": {"min_index_gap": 3, "tau_sim": 0.5}}).loop_closure
    a = np.radians(np.array([0, 6, 12, 12, 6, 1.0]))
    true = [se3.make(se3.so3_exp(np.array([0.0, ai, 0.0])), np.array([0.4 * np.sin(ai), 0.0, 0.0])) for ai in a]
    drift_step = se3.exp(np.array([0.0, 0.004, 0.002, 0.006, -0.003, 0.004]))
    gm, kfs, closer = GaussianMap(), [], LoopCloser(cfg)
    drift = np.eye(4)
    for k, T in enumerate(true):
        s = gm.new_submap(drift @ T)  # the estimated frame of this keyframe carries the drift so far
        rgbd = make_rgbd(*slam_scene.render(T, cam), cam, min_depth=0.1, max_depth=10.0)
        kf = Keyframe(k, 10 * k, float(k), s.id, np.eye(4), None, rgbd)
        s.keyframe_ids.append(k)
        kfs.append(kf)
        closer.add_keyframe(kf, kfs, gm)
        drift = drift_step @ drift
    err = lambda k: np.linalg.norm(world_pose(gm, kfs[k])[:3, 3] - true[k][:3, 3])  # noqa: E731
    before = err(5)
    accepted = closer.detect(kfs[5], kfs, gm)
    assert accepted and accepted[0].match_kf in (0, 1), [(c.match_kf, c.reason) for c in closer.log]
    closer.optimise(kfs, gm)
    assert err(0) < 1e-6  # the anchor stays
    assert sorted(closer.optimum) == list(range(6))  # every keyframe's optimum, its submap's origin placed there
    for k in kfs:
        np.testing.assert_allclose(closer.optimum[k.id], world_pose(gm, k), atol=1e-9)
    assert before > 0.02 and err(5) < 0.35 * before, (before, err(5))
    rows = closer.log_rows()
    assert all(r["reason"] for r in rows) and any(r["accepted"] for r in rows)


def test_tiny_sequence_end_to_end(tmp_path, warp_cpu):
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.dense.ply import load_ply
    from swarmsplat.slam.synthetic import GeneratorConfig, generate
    from swarmsplat.slam.io.trajectory import read_tum

    ds = generate(tmp_path / "ds", GeneratorConfig.preset("tiny", agents=1, frames=6, seed=1))
    seq = next(p for p in ds.iterdir() if p.is_dir())
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(SlamConfig().override(QUICK).to_yaml())
    out = tmp_path / "out"
    assert main(["run", str(seq), "--out", str(out), "--config", str(cfg), "--frames", "4", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    for key in ("ate_rmse", "psnr", "ssim", "depth_l1", "fps", "time_s", "psnr_input_resolution",
                "ssim_input_resolution", "depth_l1_input_resolution", "psnr_merged", "ssim_merged",
                "depth_l1_merged", "psnr_merged_input_resolution"):
        assert m[key] is not None, key
    # QUICK works at 160 px on the tiny preset's 160x120 input and maps at 80 px; evaluation is at the working
    # resolution and the input resolution, here the same (so the same figures).
    assert m["render_resolution"] == m["input_resolution"] == [160, 120]
    assert m["psnr_input_resolution"] == m["psnr"]
    assert m["frames"] == 4 and m["keyframes"] >= 1 and m["gaussians"] > 0
    assert set(m["time_s"]) >= {"tracking", "mapping", "loop_closure"}
    stamps, T = read_tum(out / "trajectory.txt")
    assert len(stamps) == 4 and np.all(np.isfinite(T))
    assert m["ate_rmse"] < 0.05  # tiny and fast, not accurate: 48 px wide, a handful of iterations
    assert len(load_ply(out / "map.ply")) == m["gaussians"]
    assert SlamConfig.from_yaml(out / "config.yaml") == SlamConfig.from_yaml(cfg)
    assert (out / "trajectory.png").is_file() and (out / "loops.csv").is_file()
    # a user error is one line and a non-zero exit, not a traceback
    assert main(["run", str(tmp_path / "missing"), "--out", str(out)]) != 0


def test_redwood_five_frames_within_a_centimetre(tmp_path, warp_cpu):
    """Real noisy depth (Augmented ICL-NUIM living room 1, 640x480): every frame's pose relative to frame 0 within
    1 cm of trajectory.log. Mapping is cut to a few iterations; it does not steer the default tracker."""
    from conftest import shared_data
    from swarmsplat.slam.io.datasets import load_sequence
    from swarmsplat.slam.run.sequence import run_sequence
    from swarmsplat.slam.io.trajectory import read_tum

    path = shared_data("redwood_livingroom1_rgbd5")
    cfg = SlamConfig().override({"mapping": {"max_width": 80, "iterations": 3, "first_iterations": 5}})
    m = run_sequence(path, tmp_path, cfg, progress=False)
    _, T = read_tum(tmp_path / "trajectory.txt")
    gt = load_sequence(path).gt_poses
    assert len(T) == len(gt) == 5 and m["skipped_frames"] == []
    for i in range(1, 5):
        E = se3.inverse(se3.inverse(gt[0]) @ gt[i]) @ (se3.inverse(T[0]) @ T[i])
        assert np.linalg.norm(E[:3, 3]) < 0.01 and np.degrees(se3.rotation_angle(E[:3, :3])) < 0.5, i


def test_single_agent_run_refines_its_merged_map(tmp_path, warp_cpu):
    """map_refine.single_agent: after the last frame the agent's merged map is optimised over its keyframes at the
    mapping resolution; metrics.json records the steps and time, and the merged map's keyframe PSNR goes up
    against the same run without it; the own-submap scores (the mapping stage's, taken before) are unchanged."""
    from swarmsplat.slam.run.sequence import run_sequence
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    ds = generate(tmp_path / "ds", GeneratorConfig.preset("tiny", agents=1, frames=6, seed=1))
    seq = next(p for p in ds.iterdir() if p.is_dir())
    base = SlamConfig().override(QUICK)
    off = run_sequence(seq, tmp_path / "off", base.override({"map_refine": {"single_agent": False}}),
                       progress=False)
    assert off["map_refine"] is None and off["time_s"]["map_refine"] == 0.0
    cfg = base.override({"map_refine": {"single_agent": True, "iterations_per_keyframe": 6, "max_iterations": 500}})
    on = run_sequence(seq, tmp_path / "on", cfg, progress=False)
    st = on["map_refine"]
    assert st["keyframes"] == on["keyframes"] >= 1 and st["iterations"] == 6 * on["keyframes"]
    assert np.isfinite(st["loss_last"]) and st["loss_last"] < st["loss_first"]
    assert on["time_s"]["map_refine"] == st["seconds"] > 0
    assert on["ate_rmse"] == off["ate_rmse"]  # refinement moves the map, not the trajectory
    assert on["psnr_merged"] > off["psnr_merged"]
    assert on["psnr"] == off["psnr"] and on["ssim"] == off["ssim"]


def test_single_agent_refinement_region_by_region(tmp_path, warp_cpu):
    """map_refine.region_gaussians below the merged map's size: the run refines it region by region through the
    same path (slam.dense.mapping.refine -> refine_regions), records the regions in metrics.json, keeps every
    region within the bound, and the merged map gains as it does refined whole."""
    from swarmsplat.slam.run.sequence import run_sequence
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    ds = generate(tmp_path / "ds", GeneratorConfig.preset("tiny", agents=1, frames=6, seed=1))
    seq = next(p for p in ds.iterdir() if p.is_dir())
    cfg = SlamConfig().override(QUICK).override({"map_refine": {"iterations_per_keyframe": 6}})
    off = run_sequence(seq, tmp_path / "off", cfg.override({"map_refine": {"single_agent": False}}), progress=False)
    whole = run_sequence(seq, tmp_path / "whole", cfg, progress=False)
    st = whole["map_refine"]
    assert st["regions"] == 1
    bound = (st["gaussians"] - st["overlap_dropped"]) // 2
    parts = run_sequence(seq, tmp_path / "parts", cfg.override({"map_refine": {"region_gaussians": bound}}),
                         progress=False)
    sp = parts["map_refine"]
    assert sp["regions"] == 2 and 0 < sp["region_gaussians_max"] <= bound
    assert sp["iterations"] >= st["iterations"]  # every keyframe visited in each region it sees
    assert parts["ate_rmse"] == whole["ate_rmse"]
    assert parts["psnr_merged"] > off["psnr_merged"] + 0.5 * (whole["psnr_merged"] - off["psnr_merged"])


def test_trajectory_per_keyframe_follows_each_keyframes_optimum():
    """A submap's later keyframe has its own pose-graph optimum, which the rigid submap move (eq. 14) ignores: the
    per-keyframe trajectory places the frames after it by that optimum, the rigid one by the submap."""
    from types import SimpleNamespace

    from swarmsplat.slam.dense.agent import FramePose

    gm = GaussianMap()
    s = gm.new_submap(np.eye(4))
    t = lambda x, y=0.0: se3.make(np.eye(3), np.array([x, y, 0.0]))  # noqa: E731
    kfs = [Keyframe(0, 0, 0.0, s.id, t(0.0), None, None), Keyframe(1, 2, 0.2, s.id, t(1.0), None, None)]
    s.keyframe_ids += [0, 1]
    poses = [FramePose(i, 0.1 * i, s.id, t(x)) for i, x in enumerate([0.0, 0.5, 1.0, 1.5])]
    loops = SimpleNamespace(optimum={})
    agent = SimpleNamespace(poses=poses, keyframes=kfs, gmap=gm, loops=loops)
    rigid = Agent.trajectory(agent)[1]
    np.testing.assert_allclose(Agent.trajectory(agent, per_keyframe=True)[1], rigid)  # no optimum yet
    loops.optimum = {0: t(0.0), 1: t(1.0, 0.1)}
    stamps, T = Agent.trajectory(agent, per_keyframe=True)
    np.testing.assert_allclose(stamps, [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(T[:2], rigid[:2])  # frames after keyframe 0, whose optimum is where it stands
    np.testing.assert_allclose(T[2:, :3, 3], [[1.0, 0.1, 0.0], [1.5, 0.1, 0.0]])
    np.testing.assert_allclose(rigid[2:, :3, 3], [[1.0, 0.0, 0.0], [1.5, 0.0, 0.0]])
    kfs[1].T_local_refined = t(1.0, -0.2)  # a refined keyframe: its frames follow the refined pose in both modes
    np.testing.assert_allclose(Agent.trajectory(agent, per_keyframe=True)[1], Agent.trajectory(agent)[1])
    np.testing.assert_allclose(Agent.trajectory(agent)[1][3, :3, 3], [1.5, -0.2, 0.0])
