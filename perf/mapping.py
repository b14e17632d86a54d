"""perf subject "mapping": one GRAND-SLAM mapping iteration (render, eq.-3 loss with its masks, backward, Adam) at
320x240 with 60k Gaussians, and on real frames, per backend, against a peer written the plain way in the same process.

Real frames (rows with scene "hololens"): the first frames of ../shared/data/hololens_office_85_378 (a HoloLens 2
walking an office) run through an agent with the defaults (loop closure off) until its active submap holds
REAL_KEYFRAMES keyframes; the scene is that submap as mapping left it (its Gaussians seeded and optimised from the
camera's own colour and depth) and its keyframes at the mapping resolution (320x213, the frames' 3:2 aspect at the
working width), with the camera's exposure model as the agent had it. Without the shared data those rows are left
out with a note.

Generated scene (rows with scene "generated"): perf.raster.make_scene's Gaussians (spread through the frustum at
1.5-6 m, 1-3.5 px on screen at 640 px scaled to the width) render the target colour and depth of three keyframes
(the camera shifted by a few cm); the map to optimise is the same Gaussians with noise on means, colours and
opacities, in the mapper's parametrisation. "ours" is `slam.dense.mapping.mapper.Mapper.optimise`, the mapping loop
the agent runs (iteration cost = the time difference between a long and a short run, divided by the extra
iterations, so Adam's and the targets' set-up are not counted); the peer is the same step written with torch's
default Adam and the eq.-3 loss from slam.dense.render.rgbd_loss, as the mapper did before. The split (render /
loss / backward / Adam) is timed on ours.
Rows per scene: Warp, Warp's scalar kernels (the CUDA ones on the CPU, `warp-scalar`) and Taichi.

Roofline row: the machine's vector arithmetic rate, measured in the same run (perf/roofline.py's `simd_gflops`:
16-lane FMA chains on both cores, before and after the backends; the higher of the two), against the
iteration's counted arithmetic: the Gaussian-pixel pairs one render composites (mean over the keyframes, the map
as the mapper starts it) times the compositing's flops per pair forward and backward (perf.raster's
FLOPS_PER_PAIR_FWD + _BWD). Lanes evaluated but not composited, the projection, binning, loss and Adam are not
counted, so achieved_gflops and roofline_fraction are lower bounds; the roofline row's iteration_ms is the time
the counted arithmetic needs at 100 % of the measured rate.

Torch runs with the pipeline's intra-op thread count (`slam.config.KernelsConfig.torch_threads`, default 1, which
`slam.run.sequence` sets): with torch's default (one thread per core) every 60k-element torch operation of the step (the
parameter activations, their backward, the medians, Adam) is a thread hand-off, and on this 2-core machine the
step measured that way was 2-3x slower than with one thread at a load of 4 (both back to back), and it is
not what the agent runs.
"""

from __future__ import annotations

import contextlib
import os
import statistics
import time

import numpy as np
import torch

DESCRIPTION = ("one mapping iteration (render + eq.-3 loss + backward + Adam) at 320x240 with 60k Gaussians, and on real "
               "frames (a HoloLens 2 submap)")

WIDTH, HEIGHT, N = 320, 240, 60_000
REAL_DATA = "hololens_office_85_378"
REAL_KEYFRAMES = 4  # keyframes of the real submap (a submap of this walk holds 4-6 at the defaults)
REAL_MAX_FRAMES = 150


@contextlib.contextmanager
def pipeline_torch_threads():
    """torch.set_num_threads as `slam.run.sequence` sets it (KernelsConfig.torch_threads; 0 = torch's default), restored
    afterwards. Yields the thread count in effect."""
    from swarmsplat.slam.config import KernelsConfig

    before = torch.get_num_threads()
    want = KernelsConfig().torch_threads
    if want:
        torch.set_num_threads(want)
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def _setup(n: int, width: int, height: int, seed: int = 0):
    """(submap, keyframes, cfg) of the scene described in the module docstring."""
    from swarmsplat.kernels import se3
    from swarmsplat.kernels.camera import PinholeCamera
    from .raster import make_scene
    from swarmsplat.slam.config import MappingConfig
    from swarmsplat.slam.dense.frames import RGBD
    from swarmsplat.slam.dense.gaussian_map import GaussianParams, Submap
    from swarmsplat.slam.dense.mapping.mapper import MapKeyframe
    from swarmsplat.slam.dense.render import render

    s = make_scene(n, width, height, seed=seed)
    K = s["K"].numpy().astype(np.float64)
    cam = PinholeCamera.from_K(K, width, height)
    g = torch.Generator().manual_seed(seed + 1)
    truth = GaussianParams(s["means"], torch.log(s["scales"]), s["quats"],
                           torch.logit(s["opacities"].clamp(1e-4, 1 - 1e-4)), s["colors"])
    keyframes = []
    for k in range(3):
        T = se3.exp(np.array([0.0, 0.01 * k, 0.0, 0.03 * k, -0.02 * k, 0.0]))  # camera-to-local
        with torch.no_grad():
            out = render(truth, torch.as_tensor(se3.inverse(T), dtype=torch.float32), cam)
        color = (out.color.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        depth = out.depth_normalised.numpy().astype(np.float32)
        keyframes.append(MapKeyframe(T, RGBD(color, depth, cam)))
    noisy = GaussianParams(truth.means + 0.005 * torch.randn(n, 3, generator=g), truth.log_scales.clone(),
                           truth.quats.clone(), truth.logit_opacities + 0.5 * torch.randn(n, generator=g),
                           (truth.colors + 0.1 * torch.randn(n, 3, generator=g)).clamp(0, 1))
    submap = Submap(0, np.eye(4), noisy, [0, 1, 2])
    return submap, keyframes, MappingConfig(), None


def _setup_real(path, keyframes: int = REAL_KEYFRAMES, max_frames: int = REAL_MAX_FRAMES):
    """(submap, keyframes, mapping cfg, exposure cfg or None) from real frames: see the module docstring."""
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.dense.agent import Agent
    from swarmsplat.slam.io.datasets import load_sequence

    seq = load_sequence(path)
    cfg = SlamConfig()
    cfg.loop_closure.enabled = False
    agent = Agent(seq.camera, cfg, name="mapping-scene")
    for i in range(min(len(seq), max_frames)):
        f = seq[i]
        agent.step(i, f.timestamp, f.color, f.depth)
        if agent.gmap.active is not None and len(agent.gmap.active.keyframe_ids) >= keyframes:
            break
    else:
        raise RuntimeError(f"{path}: no submap reached {keyframes} keyframes in its first {max_frames} frames")
    submap = agent.gmap.active
    return submap, agent.map_keyframes(submap), agent.mapper.cfg, agent.mapper.exposure


def _optimise_s(submap, keyframes, cfg, iterations: int, exposure=None) -> float:
    """Seconds of `iterations` steps of Mapper.optimise (with the camera's exposure model where the scene has one);
    the submap's parameters and the keyframes' exposures are put back afterwards."""
    from swarmsplat.slam.dense.mapping.mapper import Mapper

    start = submap.params
    exposures = [None if k.exposure is None else k.exposure.copy() for k in keyframes]
    t0 = time.perf_counter()
    Mapper(cfg, exposure).optimise(submap, keyframes, iterations)
    dt = time.perf_counter() - t0
    submap.params = start
    for k, e in zip(keyframes, exposures):
        if e is not None:
            k.exposure[:] = e
    return dt


def _peer_step_s(submap, keyframes, cfg, iterations: int) -> float:
    """The plain loop: torch's default Adam, torch's activations, slam.dense.render.rgbd_loss + the isotropic penalty, one
    keyframe a step."""
    from swarmsplat.kernels import use_reference
    from swarmsplat.slam.dense.param_ops import activate
    from swarmsplat.slam.dense.render import render, rgbd_loss, viewmat_from_pose

    p = submap.params.detached().requires_grad_(True)
    opt = torch.optim.Adam([{"params": [p.means], "lr": cfg.lr_means}, {"params": [p.log_scales], "lr": cfg.lr_log_scales},
                            {"params": [p.quats], "lr": cfg.lr_quats},
                            {"params": [p.logit_opacities], "lr": cfg.lr_opacities},
                            {"params": [p.colors], "lr": cfg.lr_colors}], eps=1e-15)
    targets = [(viewmat_from_pose(k.T_local_cam), k.rgbd.color_tensor(), k.rgbd.depth_tensor(), k.rgbd.camera)
               for k in keyframes]
    t0 = time.perf_counter()
    for i in range(iterations):
        vm, color, depth, cam = targets[i % len(targets)]
        opt.zero_grad(set_to_none=True)
        with use_reference():  # torch's exp, sigmoid and clamp (the twin); the rasteriser stays on the backend
            act = activate(p)
        out = render(p, vm, cam, activated=act)
        loss = rgbd_loss(out, color, depth, lambda_color=cfg.lambda_color, alpha_power=cfg.alpha_power,
                         inlier_k=cfg.inlier_k)
        s = p.scales
        loss = loss + cfg.isotropic_regulariser * (s - s.mean(dim=1, keepdim=True)).abs().mean()
        loss.backward()
        opt.step()
        float(loss.detach())
    return (time.perf_counter() - t0) / iterations


def _split_ms(submap, keyframes, cfg, iterations: int) -> dict:
    """Median per-stage wall times of `iterations` steps of the mapper's own pieces."""
    from swarmsplat.slam.dense.mapping.mapper import make_optimizer, mapping_loss
    from swarmsplat.slam.dense.param_ops import activate
    from swarmsplat.slam.dense.render import render, viewmat_from_pose

    p = submap.params.detached().requires_grad_(True)
    opt = make_optimizer(p, cfg)
    targets = [(viewmat_from_pose(k.T_local_cam), k.rgbd.color_tensor(), k.rgbd.depth_tensor(), k.rgbd.camera)
               for k in keyframes]
    stages = {"render_ms": [], "loss_ms": [], "backward_ms": [], "adam_ms": []}
    for i in range(iterations):
        vm, color, depth, cam = targets[i % len(targets)]
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        act = activate(p)
        out = render(p, vm, cam, activated=act)
        t1 = time.perf_counter()
        loss = mapping_loss(out, color, depth, p, cfg, cfg.lambda_color, cfg.isotropic_regulariser, act)
        t2 = time.perf_counter()
        loss.backward()
        t3 = time.perf_counter()
        opt.step()
        float(loss.detach())
        t4 = time.perf_counter()
        for k, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            stages[k].append(1e3 * dt)
    return {k: statistics.median(v[1:]) for k, v in stages.items()}


def _pairs_per_render(submap, keyframes) -> float:
    """Mean Gaussian-pixel pairs one render of a keyframe composites (kernels.rasterize's n_touched), the map as
    the mapper starts it, on the active backend."""
    from swarmsplat.kernels import rasterize
    from swarmsplat.slam.dense.param_ops import activate
    from swarmsplat.slam.dense.render import viewmat_from_pose

    p = submap.params
    with torch.no_grad():
        a = activate(p)
        pairs = [int(rasterize(p.means, p.quats, a.scales, a.opacities, a.colors, viewmat_from_pose(k.T_local_cam),
                               torch.as_tensor(k.rgbd.camera.K, dtype=torch.float32), k.rgbd.camera.width,
                               k.rgbd.camera.height).n_touched.sum())
                 for k in keyframes]
    return statistics.mean(pairs)


def run_with_pipeline_threads(fn, **kwargs) -> dict:
    """A subject's run(**kwargs) under pipeline_torch_threads, with a note saying the thread count."""
    with pipeline_torch_threads() as threads:
        out = fn(**kwargs)
    out["notes"].append(f"torch intra-op threads: {threads} (slam.config.KernelsConfig.torch_threads, as slam.run.sequence "
                        "sets it; the torch operations around the kernels run on it)")
    return out


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    return run_with_pipeline_threads(_run, backends=backends, device=device, quick=quick)


def _scenes(n: int, notes: list) -> list:
    """[(name, (submap, keyframes, cfg, exposure))]: the generated scene, and the real frames' where the shared data
    is (a note says why not otherwise)."""
    from .common import shared_data

    scenes = [("generated", _setup(n, WIDTH, HEIGHT))]
    try:
        path = shared_data(REAL_DATA, "mapping")
    except SystemExit as e:
        notes.append(f"real-frames rows left out: {e}")
        return scenes
    scenes.append(("hololens", _setup_real(path)))
    return scenes


def _image(keyframes) -> str:
    cam = keyframes[0].rgbd.camera
    return f"{cam.width}x{cam.height}"


def _run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .common import SCALAR_PEER, use_backend, with_scalar_peer
    from .raster import FLOPS_PER_PAIR_BWD, FLOPS_PER_PAIR_FWD
    from .roofline import fma_gflops, simd_gflops

    if device != "cpu":
        from swarmsplat.kernels.errors import BackendError

        raise BackendError("perf mapping runs on the CPU (the mapper keeps its maps on the CPU)")
    n = 20_000 if quick else N
    short, long_, repeat = (3, 8, 2) if quick else (5, 30, 3)
    rows = []
    notes = [f"load average at start (1 min, all users): {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"]
    backends = with_scalar_peer(backends, device)
    use_backend(backends[0], device)
    scenes = _scenes(n, notes)
    peak, scalar = _probe(backends, device, fma_gflops, simd_gflops)
    per_scene = {}
    for scene, (submap, keyframes, cfg, exposure) in scenes:
        use_backend(backends[0], device)
        pairs = _pairs_per_render(submap, keyframes)
        per_scene[scene] = (pairs, pairs * (FLOPS_PER_PAIR_FWD + FLOPS_PER_PAIR_BWD) / 1e9, _image(keyframes),
                            len(submap.params))
        for name in backends:
            use_backend(name, device)
            _optimise_s(submap, keyframes, cfg, 2, exposure)  # warm-up: compiles / loads the kernels
            per_it = []
            c0 = time.process_time()
            for _ in range(repeat):
                t_short = _optimise_s(submap, keyframes, cfg, short, exposure)
                t_long = _optimise_s(submap, keyframes, cfg, long_, exposure)
                per_it.append((t_long - t_short) / (long_ - short))
            cpu_ms = 1e3 * (time.process_time() - c0) / (repeat * (short + long_))
            ours = statistics.median(per_it)
            peer = statistics.median(_peer_step_s(submap, keyframes, cfg, short) for _ in range(repeat))
            row = {"scene": scene, "backend": name, "image": _image(keyframes), "N": len(submap.params),
                   "iteration_ms": 1e3 * ours, "iterations_per_s": 1.0 / ours, "iteration_cpu_ms": cpu_ms,
                   "peer_iteration_ms": 1e3 * peer, "speedup": peer / ours}
            row.update(_split_ms(submap, keyframes, cfg, short + 1))
            rows.append(row)
            use_backend(backends[0], device)
            print(f"[perf mapping] {scene} {name}: {1e3 * ours:.1f} ms per iteration (peer {1e3 * peer:.1f} ms)",
                  flush=True)
    notes += [
        f"load average at end: {os.getloadavg()[0]:.1f}; iteration_cpu_ms = process CPU time (all threads) per "
        "iteration including set-up, less sensitive to other users than wall time",
        f"iteration_ms: (time of Mapper.optimise with {long_} iterations - with {short}) / {long_ - short}, median "
        f"of {repeat}, with the camera's exposure model where the scene's agent had it on (hololens); the split "
        "columns are medians of single steps of the same pieces without it (not additive to it exactly)",
        "peer: the same step with torch.optim.Adam defaults and slam.dense.render.rgbd_loss, keyframes in turn, same "
        "process and scene, no exposure model",
    ]
    peak2, scalar2 = _probe(backends, device, fma_gflops, simd_gflops)
    peak = max(peak, peak2)
    for row in rows:
        gflop = per_scene[row["scene"]][1]
        row["gflop_per_iteration"] = gflop
        row["achieved_gflops"] = gflop / (row["iteration_ms"] / 1e3)
        row["roofline_fraction"] = row["achieved_gflops"] / peak
    for scene, (pairs, gflop, image, n_scene) in per_scene.items():
        rows.append({"scene": scene, "backend": "roofline", "image": image, "N": n_scene,
                     "iteration_ms": 1e3 * gflop / peak, "gflop_per_iteration": gflop, "achieved_gflops": peak,
                     "roofline_fraction": 1.0})
        notes.append(f"{scene}: counted arithmetic {pairs / 1e6:.2f} M composited pairs per render x "
                     f"{FLOPS_PER_PAIR_FWD + FLOPS_PER_PAIR_BWD} flops = {gflop:.3f} GFLOP per iteration")
    notes.append(f"roofline: {peak:.1f} GFLOP/s measured on the CPU's vector units in this run (16-lane float32 FMA "
                 f"chains, both cores; scalar FMA chains: {max(scalar, scalar2):.1f} GFLOP/s); the counted "
                 "arithmetic is a lower bound (see the module docstring); a roofline row's iteration_ms is that "
                 "arithmetic at 100 % of the measured rate")
    scalar = {r["scene"]: r for r in rows if r["backend"] == SCALAR_PEER}
    for row in rows:
        if row["backend"] == "warp" and row["scene"] in scalar:
            row["vs_scalar"] = scalar[row["scene"]]["iteration_ms"] / row["iteration_ms"]
    if scalar:
        notes.append(f"{SCALAR_PEER}: Warp with its own compositing, projection, binning, activation and loss "
                     "kernels (the CUDA ones, scalar code on the CPU, the loss included); "
                     "vs_scalar = its iteration_ms / warp's, same run and scene")
    columns = ["scene", "backend", "image", "N", "iteration_ms", "iterations_per_s", "iteration_cpu_ms", "render_ms",
               "loss_ms", "backward_ms", "adam_ms", "peer_iteration_ms", "speedup", "vs_scalar",
               "gflop_per_iteration", "achieved_gflops", "roofline_fraction"]
    return {"rows": rows, "columns": columns, "notes": notes}


def _probe(backends: list[str], device: str, fma_gflops, simd_gflops) -> tuple[float, float]:
    """(vector GFLOP/s, scalar GFLOP/s) of the machine now: the vector probe needs Warp (a Taichi-only install
    reports its scalar probe for both)."""
    from .common import use_backend

    base = use_backend(backends[0], device)
    scalar = fma_gflops(base, device)
    if base != "warp":
        return scalar, scalar
    return simd_gflops(), scalar
