"""`generate(out_dir, config)`: render every agent and write a dataset in our folder format, atomically.

Layout (read by slam.io.datasets.folder):

    out_dir/dataset.yaml        {name, kind: rgbd|mono, agents: [agent_0, ...], seed, generator: {settings}}
    out_dir/agent_k/rgb/000000.png      8-bit RGB
    out_dir/agent_k/depth/000000.png    uint16, metres = value / depth_scale, 0 = hole     (RGB-D only)
    out_dir/agent_k/rgb.txt, depth.txt  TUM lists ('timestamp rgb/000000.png')
    out_dir/agent_k/groundtruth.txt     TUM, T_world_cam (OpenCV camera axes, z-up world)
    out_dir/agent_k/odometry.txt        TUM, T_odom_cam, odometry frame = first camera frame (mono only)
    out_dir/agent_k/calibration.yaml    fx fy cx cy width height [depth_scale]

The dataset is built in a hidden folder beside `out_dir` and renamed into place at the end, so a reader never
sees half a dataset and a failure leaves any previous dataset intact. An existing `out_dir` is replaced only
if it is empty or is itself a dataset (has `dataset.yaml`). Same seed and settings give identical bytes.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.trajectory import write_tum

from .config import GeneratorConfig
from .mono import drifting_odometry
from .noise import depth_to_uint16, frame_rng, noisy_color, noisy_depth
from .render import camera_for, combine, shade, shade_color, supersampled, trace
from .trajectories import agent_trajectory
from .world import World, generate_world

_BATCH = 4  # frames ray-cast per call
# Fast settings (Huffman-only deflate is quicker than level 1 and, on these noisy images, as small);
# output bytes are still deterministic.
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]


def dataset_camera(config: GeneratorConfig) -> PinholeCamera:
    """The pinhole camera of every agent: width x height, `hfov_deg` field of view, centred principal point."""
    return camera_for(config.width, config.height, config.hfov_deg)


def agent_poses(world: World, config: GeneratorConfig) -> list[np.ndarray]:
    """Ground-truth T_world_cam [frames, 4, 4] of each agent."""
    return [agent_trajectory(world.loops[a], config.frames, config.motion) for a in range(config.agents)]


def generate(out_dir: str | os.PathLike, config: GeneratorConfig | None = None, *,
             progress: Callable[[int], None] | None = None) -> Path:
    """Write the dataset described by `config` to `out_dir` and return its path.

    progress: called with the number of frames just finished (e.g. a progress bar's `update`, slam.io.progress).
    Raises InputError if `out_dir` is a file or a non-empty folder that is not a dataset.
    """
    config = config or GeneratorConfig()
    out = Path(out_dir).resolve()  # a name and a real parent folder even for "." or "sub/"
    check_output_dir(out)
    world = generate_world(config.seed, config.world)
    camera = dataset_camera(config)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        names = [f"agent_{a}" for a in range(config.agents)]
        for a, (name, poses) in enumerate(zip(names, agent_poses(world, config))):
            _write_agent(tmp / name, world, camera, poses, a, config, progress)
        meta = {"name": config.name, "kind": config.kind, "agents": names, "seed": config.seed,
                "generator": config.model_dump(mode="json")}
        (tmp / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; a dataset is an ordinary folder
        _swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def check_output_dir(out: str | os.PathLike) -> None:
    """Raise InputError unless `out` is absent, an empty folder, or a dataset (which generate may replace)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output path {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "dataset.yaml").is_file():
        raise InputError(f"output folder {out} is not empty and holds no dataset.yaml; refusing to overwrite it "
                         "(choose an empty or new folder)")


def _swap_into_place(tmp: Path, out: Path) -> None:
    if not out.exists():
        os.replace(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    old.rmdir()
    os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.replace(old, out)  # put the previous dataset back
        raise
    shutil.rmtree(old, ignore_errors=True)


def _write_agent(folder: Path, world: World, camera: PinholeCamera, poses: np.ndarray, agent: int,
                 config: GeneratorConfig, progress) -> None:
    (folder / "rgb").mkdir(parents=True)
    if not config.mono:
        (folder / "depth").mkdir()
    n = len(poses)
    stamps = np.arange(n) / config.fps
    files = [f"{k:06d}.png" for k in range(n)]
    # Texturing, noise and PNG encoding (NumPy and OpenCV release the GIL) run in worker threads while the
    # main thread ray-casts the next batch. Each frame's noise comes from its own seeded generator, so the
    # bytes do not depend on timing.
    ss = config.supersample
    fine = supersampled(camera, ss)

    def finish(start: int, traced) -> int:
        centre, sub = traced
        hits = shade(world, centre, camera) if sub is None else combine(
            shade(world, centre, camera, texture=False), shade_color(world, sub, fine), ss)
        for j in range(len(hits.depth)):
            k = start + j
            rng = frame_rng(config.seed, agent, k)
            rgb = noisy_color(hits.color[j], config.color_noise, rng)
            _write_png(folder / "rgb" / files[k], cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            if not config.mono:
                depth = noisy_depth(hits.depth[j], hits.cos_incidence[j], config.depth_noise, rng)
                _write_png(folder / "depth" / files[k], depth_to_uint16(depth, config.depth_scale))
        return len(hits.depth)

    _ = world.texture  # build the shared texture once, before the worker threads read it
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending: list[Future] = []
        for start in range(0, n, _BATCH):
            batch = poses[start : start + _BATCH]
            traced = (trace(world, batch, camera), trace(world, batch, fine) if ss > 1 else None)
            pending.append(pool.submit(finish, start, traced))
            while len(pending) > 2:  # bound the memory held by batches waiting to be textured
                done = pending.pop(0).result()
                if progress:
                    progress(done)
        for f in pending:
            done = f.result()
            if progress:
                progress(done)

    (folder / "rgb.txt").write_text(_image_list("color", "rgb", stamps, files))
    if not config.mono:
        (folder / "depth.txt").write_text(_image_list("depth", "depth", stamps, files))
    write_tum(folder / "groundtruth.txt", stamps, poses)
    calib = {k: float(v) for k, v in camera.to_dict().items()}
    calib["width"], calib["height"] = camera.width, camera.height
    if config.mono:
        odom = drifting_odometry(poses, config.odometry, np.random.default_rng([config.seed, agent, 5]))
        write_tum(folder / "odometry.txt", stamps, odom)
    else:
        calib["depth_scale"] = float(config.depth_scale)
    (folder / "calibration.yaml").write_text(yaml.safe_dump(calib, sort_keys=False))


def _image_list(what: str, sub: str, stamps: np.ndarray, files: list[str]) -> str:
    head = f"# synthetic {what} images written by swarmsplat generate\n# timestamp filename\n"
    return head + "".join(f"{t:.6f} {sub}/{f}\n" for t, f in zip(stamps, files))


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image, PNG_PARAMS)
    if not ok:
        raise OSError(f"PNG encoding failed for {path}")
    path.write_bytes(buf.tobytes())
