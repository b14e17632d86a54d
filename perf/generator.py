"""Synthetic generator throughput at 320x240: our full pipeline against Open3D's bare ray cast of one ray per pixel.

The generator runs on NumPy, Open3D and one Warp CPU kernel (the texture) whatever kernel backend or device is
chosen, so `backends` and `device` only label the run. Target: >= 20 frames/s for the whole pipeline on
a 2-core machine. Rows at the default `supersample` (rays per pixel side, colour averaged over the pixel) and at 1
(one ray through each pixel centre, the generator before supersampling).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import time_fn

DESCRIPTION = "synthetic RGB-D generator, frames/s at 320x240 (peer: Open3D RaycastingScene ray cast alone)"

_TARGET_FPS = 20.0


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import cv2
    import open3d as o3d

    from swarmsplat.kernels import se3
    from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, cast, dataset_camera, generate, generate_world
    from swarmsplat.slam.synthetic.noise import depth_to_uint16, frame_rng, noisy_color, noisy_depth
    from swarmsplat.slam.synthetic.writer import PNG_PARAMS

    cfg = GeneratorConfig.preset("default", agents=1, frames=16 if quick else 48)
    world = generate_world(cfg.seed, cfg.world)
    camera = dataset_camera(cfg)
    poses = agent_poses(world, cfg)[0]
    batch = poses[:4]
    repeat = 3 if quick else 7
    K = o3d.core.Tensor(camera.K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]))

    def raycast_only():  # the peer: Open3D generating and casting the same rays, nothing else
        for T in batch:
            rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(K, o3d.core.Tensor(se3.inverse(T)),
                                                                      camera.width, camera.height)
            world.scene.cast_rays(rays)["t_hit"].numpy()

    ss = cfg.supersample
    fine = camera.scaled(camera.width * ss, camera.height * ss)
    K_fine = o3d.core.Tensor(fine.K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]))

    def raycast_fine():  # the same bare cast of the default's rays: the centre ray and ss x ss over the pixel
        raycast_only()
        for T in batch:
            rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(K_fine, o3d.core.Tensor(se3.inverse(T)),
                                                                      fine.width, fine.height)
            world.scene.cast_rays(rays)["t_hit"].numpy()

    def render_one_ray():
        cast(world, batch, camera)

    def render():
        cast(world, batch, camera, ss)

    def render_noise_encode():
        hits = cast(world, batch, camera, ss)
        for j in range(len(batch)):
            rng = frame_rng(0, 0, j)
            rgb = noisy_color(hits.color[j], cfg.color_noise, rng)
            depth = noisy_depth(hits.depth[j], hits.cos_incidence[j], cfg.depth_noise, rng)
            cv2.imencode(".png", rgb, PNG_PARAMS)
            cv2.imencode(".png", depth_to_uint16(depth, cfg.depth_scale), PNG_PARAMS)

    tmp = Path(tempfile.mkdtemp(prefix="perf_generator_"))
    try:
        def end_to_end():  # world build, all frames, PNG + text files on disk, atomic rename
            generate(tmp / "ds", cfg)

        one_ray = GeneratorConfig.preset("default", agents=1, frames=cfg.frames, supersample=1)

        def end_to_end_one_ray():
            generate(tmp / "ds1", one_ray)

        stages = [
            ("Open3D ray cast only, 1 ray per pixel (peer)", raycast_only, len(batch)),
            ("ray cast + texture, 1 ray per pixel", render_one_ray, len(batch)),
            (f"Open3D ray cast only, 1 + {ss}x{ss} rays per pixel", raycast_fine, len(batch)),
            (f"ray cast + texture, {ss}x{ss} rays per pixel (default)", render, len(batch)),
            ("+ sensor noise + PNG encoding", render_noise_encode, len(batch)),
            (f"generate() end to end, 1 ray per pixel, {cfg.frames} frames to disk", end_to_end_one_ray, cfg.frames),
            (f"generate() end to end, default ({ss}x{ss} rays), {cfg.frames} frames to disk", end_to_end, cfg.frames),
        ]
        rows = []
        peer = None
        for name, fn, frames in stages:
            cpu0 = time.process_time()
            t = time_fn(fn, repeat=repeat if frames == len(batch) else max(2, repeat // 2), warmup=1)
            cpu = (time.process_time() - cpu0) / (t["runs"] + 1) / frames  # all threads, warm-up included
            per_frame = t["median_s"] / frames
            peer = peer or per_frame
            rows.append({"stage": name, "ms_per_frame": 1000 * per_frame, "frames_per_s": 1.0 / per_frame,
                         "x_peer_time": per_frame / peer, "cpu_ms_per_frame": 1000 * cpu, "runs": t["runs"]})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    fps = rows[-1]["frames_per_s"]
    notes = [
        f"target >= {_TARGET_FPS:.0f} frames/s for the whole pipeline: {'met' if fps >= _TARGET_FPS else 'NOT met'} "
        f"({fps:.1f} frames/s end to end)",
        "x_peer_time = our time per frame / Open3D's bare ray-cast time per frame (ratio of medians, same process)",
        "cpu_ms_per_frame = process CPU time (all threads) per frame: on a shared machine the wall-clock numbers "
        "include waiting for other processes, the CPU time does not",
        f"default supersample {ss}: each pixel's colour is the mean of {ss * ss} rays over its area, depth the "
        "centre ray's (one ray per pixel aliased edges and textures: 28.6-31.3 dB from the pixel's area mean)",
        f"NumPy, Open3D and a Warp CPU kernel; independent of --kernels ({', '.join(backends)}) and --device "
        f"({device})",
    ]
    return {"rows": rows,
            "columns": ["stage", "ms_per_frame", "frames_per_s", "x_peer_time", "cpu_ms_per_frame", "runs"],
            "notes": notes}
