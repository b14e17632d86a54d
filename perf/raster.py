"""Gaussian rasteriser benchmark: forward and forward+backward on each backend against a tile-based torch peer,
Gaussian-pixel pairs per second, the fraction of a compute roofline measured in the same run, and the per-call
floor (160x120, 1k Gaussians).

The peer (`torch_tiles_rasterize` below) is the straightforward vectorised torch implementation of the same
3DGS rules: the same projection, then per 16x16 tile one batched [pixels, Gaussians] alpha matrix, a cumprod
for transmittance (with the 1e-4 stop), a matmul for colour and depth, and autograd for the backward. It runs
in the same process on the same scene; ratios are of medians after warm-up.

Roofline: perf/roofline.py's fused-multiply-add loop compiled by the same backend, run before and after the
cases (median of both). The fraction is pairs/s x the arithmetic the kernels do per composited pair (counted in
their source: FLOPS_PER_PAIR_FWD / _BWD, exp() counted as 10) over the loop's flop rate. Pixels that are
evaluated but not composited are not counted, so the fraction is a lower bound. The loop is scalar code (one
work item per thread, as the kernels: neither backend's CPU code generator vectorises across work items), so it
is the scalar FMA roofline; `roofline_bound_fwd_bwd_ms` is the forward+backward time the counted arithmetic needs
at 100 % of it — a speed-up target below that needs SIMD code.
"""

from __future__ import annotations

import math
import os
import sys
import time

import torch

from .common import time_fn

DESCRIPTION = "kernels.rasterize (colour+depth+alpha, 3DGS rules): forward and forward+backward vs a tile-based torch peer"

TILE = 16
PEER_MAX_N = 10_000  # the peer takes minutes per call above this (640x480 / 50k: 145 s forward, quiet machine)
FLOPS_PER_PAIR_FWD = 33  # power 10, exp 10, alpha 2, transmittance 2, weight 1, colour + depth 8
FLOPS_PER_PAIR_BWD = 67  # the backward kernel's per-pair arithmetic (exp again, 1 / (1 - a), ten gradient sums)
FLOOR_CASE = (160, 120, 1_000)
PEER_BUDGET_S = 900.0  # wall-time budget for all peer runs


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """n Gaussians spread through the view frustum at 1.5-6 m, sized to 1-3.5 px standard deviation on screen
    (kernels.selfcheck.frustum_scene: the device self-check renders the same kind of scene)."""
    from swarmsplat.kernels.selfcheck import frustum_scene

    return frustum_scene(n, width, height, seed)


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:  # [N, 4] wxyz -> [N, 3, 3]
    q = q * torch.rsqrt((q * q).sum(-1, keepdim=True))
    w, x, y, z = q.unbind(-1)
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    return torch.stack(
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
         2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
         2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], -1).reshape(-1, 3, 3)


def torch_project(means, quats, scales, viewmat, K, width: int, height: int, near: float, far: float):
    """The peer's EWA projection (torch, float32, autograd). Returns mean2d [N,2], conic [N,3] (a, b, c of the inverse 2D covariance),
    z [N], radius [N] int32, rect [N,4] int32 tile range (x0, y0, x1, y1; ends exclusive), visible [N] bool."""
    R_v, t_v = viewmat[:3, :3], viewmat[:3, 3]
    p = torch.addmm(t_v, means, R_v.T)  # [N, 3] camera frame
    x, y, z = p.unbind(-1)
    valid = (z >= near) & (z <= far)
    zs = torch.where(valid, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # 3DGS clamps the Jacobian's x/z, y/z to 1.3x the field of view so off-axis giants stay bounded.
    lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    inv_z = 1.0 / zs
    u = torch.minimum(torch.maximum(x * inv_z, -(cx / fx + lim_x)), (width - cx) / fx + lim_x)
    v = torch.minimum(torch.maximum(y * inv_z, -(cy / fy + lim_y)), (height - cy) / fy + lim_y)
    # T = J R_v R(q) S: rows of the 2x3 map from the Gaussian's unit frame to pixels.
    Mc = torch.matmul(R_v, _quat_to_rotmat(quats)) * scales[:, None, :]  # [N, 3, 3]
    T0 = (fx * inv_z)[:, None] * (Mc[:, 0] - u[:, None] * Mc[:, 2])  # [N, 3]
    T1 = (fy * inv_z)[:, None] * (Mc[:, 1] - v[:, None] * Mc[:, 2])
    a = (T0 * T0).sum(-1) + 0.3
    b = (T0 * T1).sum(-1)
    c = (T1 * T1).sum(-1) + 0.3
    det = a * c - b * b
    visible = valid & (det > 0)
    inv_det = 1.0 / torch.where(visible, det, torch.ones_like(det))
    conic = torch.stack([c * inv_det, -b * inv_det, a * inv_det], -1)
    mean2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))))
        ntx, nty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        m = mean2d.detach()
        x0 = torch.floor((m[:, 0] - radius) / TILE).clamp(0, ntx)
        x1 = (torch.floor((m[:, 0] + radius) / TILE) + 1).clamp(0, ntx)
        y0 = torch.floor((m[:, 1] - radius) / TILE).clamp(0, nty)
        y1 = (torch.floor((m[:, 1] + radius) / TILE) + 1).clamp(0, nty)
        visible = visible & (x1 > x0) & (y1 > y0)
        rect = torch.stack([x0, y0, x1, y1], -1).to(torch.int32)
        radius = torch.where(visible, radius.clamp(max=2**30), torch.zeros_like(radius)).to(torch.int32)
    return mean2d, conic, z, radius, rect, visible


def torch_tiles_rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height):
    """The peer: per-tile vectorised torch compositing with autograd; returns (color, depth, alpha)."""
    mean2d, conic, z, _radius, rect, visible = torch_project(means, quats, scales, viewmat, K, width, height, 0.01, 100.0)
    idx = torch.nonzero(visible).squeeze(1)
    idx = idx[torch.sort(z.detach()[idx], stable=True).indices]
    m2, cn, zz, op, col, rc = mean2d[idx], conic[idx], z[idx], opacities[idx], colors[idx], rect[idx]
    color_rows, depth_rows, alpha_rows = [], [], []
    for ty in range(math.ceil(height / TILE)):
        c_row, d_row, a_row = [], [], []
        for tx in range(math.ceil(width / TILE)):
            sel = torch.nonzero((rc[:, 0] <= tx) & (rc[:, 2] > tx) & (rc[:, 1] <= ty) & (rc[:, 3] > ty)).squeeze(1)
            ys, xs = torch.meshgrid(torch.arange(ty * TILE, min(height, ty * TILE + TILE)),
                                    torch.arange(tx * TILE, min(width, tx * TILE + TILE)), indexing="ij")
            dx = xs.reshape(-1, 1).float() - m2[sel, 0]
            dy = ys.reshape(-1, 1).float() - m2[sel, 1]
            power = -0.5 * (cn[sel, 0] * dx * dx + cn[sel, 2] * dy * dy) - cn[sel, 1] * dx * dy
            a = torch.clamp(op[sel] * torch.exp(torch.clamp(power, max=0.0)), max=0.99)
            a = torch.where((power <= 0) & (a >= 1 / 255), a, torch.zeros_like(a))
            with torch.no_grad():
                live = torch.cumprod(1 - a, 1) >= 1e-4
            a = a * live
            T = torch.cumprod(1 - a, 1)
            w = a * torch.cat([torch.ones_like(T[:, :1]), T[:, :-1]], 1)
            tf = T[:, -1] if sel.numel() else torch.ones(a.shape[0])
            shape = ys.shape
            c_row.append((w @ col[sel]).reshape(*shape, 3))
            d_row.append((w @ zz[sel]).reshape(shape))
            a_row.append((1 - tf).reshape(shape))
        color_rows.append(torch.cat(c_row, 1))
        depth_rows.append(torch.cat(d_row, 1))
        alpha_rows.append(torch.cat(a_row, 1))
    return torch.cat(color_rows, 0), torch.cat(depth_rows, 0), torch.cat(alpha_rows, 0)


def _params(scene, grad: bool):
    out = dict(scene)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        out[k] = scene[k].clone().requires_grad_(grad)
    return out


def _loss(color, depth, alpha):
    return color.sum() + 0.1 * depth.sum() + alpha.sum()


def _ours(scene, backward: bool, count: bool = False):
    """One kernels.rasterize call as the pipeline makes it (count_touched=False, as slam.dense.render does); count=True
    also counts each Gaussian's pixels (n_touched), for pairs_M."""
    from swarmsplat import kernels

    p = _params(scene, backward)
    o = kernels.rasterize(**p, count_touched=count)
    if backward:
        _loss(o.color, o.depth, o.alpha).backward()
    return o


def _peer(scene, backward: bool):
    p = _params(scene, backward)
    with torch.set_grad_enabled(backward):
        c, d, a = torch_tiles_rasterize(**p)
        if backward:
            _loss(c, d, a).backward()
    return c


def _log(msg: str) -> None:
    print(f"[perf raster] {msg}", file=sys.stderr, flush=True)


def _floor(scene, repeat: int) -> tuple[dict, dict]:
    """Per-call floor: kernels.rasterize forward, and forward + backward from fixed upstream gradients (no loss
    ops), median of `repeat` calls."""
    from swarmsplat import kernels

    p = _params(scene, True)
    o = kernels.rasterize(**p, count_touched=False)
    grads = [torch.rand_like(o.color), torch.rand_like(o.depth), torch.rand_like(o.alpha)]

    def fwd():
        with torch.no_grad():
            kernels.rasterize(**p, count_touched=False)

    def fwd_bwd():
        out = kernels.rasterize(**p, count_touched=False)
        torch.autograd.backward([out.color, out.depth, out.alpha], grads)

    res = []
    for fn in (fwd, fwd_bwd):
        for _ in range(3):  # warm-up outside the CPU clock: a first call can load modules (~0.5 s of CPU)
            fn()
        c0 = time.process_time()
        r = time_fn(fn, repeat=repeat, warmup=0)
        r["cpu_s"] = (time.process_time() - c0) / r["runs"]  # CPU seconds of all threads per call
        res.append(r)
    return res[0], res[1]


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .mapping import run_with_pipeline_threads

    return run_with_pipeline_threads(_run, backends=backends, device=device, quick=quick)


def _run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .common import SCALAR_PEER, TAICHI_SCALAR_PEER, use_backend, with_scalar_peer
    from .roofline import fma_gflops

    backends = with_scalar_peer(backends, device)
    if device == "cpu" and "taichi" in backends:  # Taichi's vector compositing against its scalar kernels
        i = backends.index("taichi")
        backends = backends[:i + 1] + [TAICHI_SCALAR_PEER] + backends[i + 1:]

    cases = [(320, 240, 10_000)] if quick else [(640, 480, 50_000), (640, 480, 10_000), (320, 240, 60_000),
                                                (320, 240, 10_000)]
    repeat = 3 if quick else 5
    rows, notes = [], [f"load average at start (1 min, all users): {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"]
    roof = {}
    for name in backends:
        roof[name] = [fma_gflops(use_backend(name, device), device)]
    # Ours first on every size, then the peer (seconds per call) within PEER_BUDGET_S of wall time.
    for width, height, n in cases:
        scene = make_scene(n, width, height)
        if device == "cuda":
            scene = {k: v.cuda() if isinstance(v, torch.Tensor) else v for k, v in scene.items()}
        for name in backends:
            use_backend(name, device)
            # three warm-up calls: the first calls at a new size also pay the allocator's first page faults of the
            # large buffers (glibc maps them fresh until its mmap threshold has grown), which one did not cover
            f = time_fn(lambda: _ours(scene, False), repeat=repeat, warmup=3, device=device)
            _ours(scene, True)  # outside the CPU clock: the first backward may compile its kernels (Taichi: seconds)
            c0 = time.process_time()
            fb = time_fn(lambda: _ours(scene, True), repeat=repeat, warmup=1, device=device)
            fb_cpu = (time.process_time() - c0) / (fb["runs"] + 1)  # CPU seconds of all threads per call
            o = _ours(scene, False, count=True)
            touched = int(o.n_touched.sum())
            rows.append({"backend": name, "image": f"{width}x{height}", "N": n, "visible": int((o.radii > 0).sum()),
                         "pairs_M": touched / 1e6, "fwd_ms": 1e3 * f["median_s"], "fwd_bwd_ms": 1e3 * fb["median_s"],
                         "fwd_bwd_cpu_ms": 1e3 * fb_cpu, "Mpairs_per_s_fwd": touched / f["median_s"] / 1e6,
                         "Mpairs_per_s_fwd_bwd": touched / fb["median_s"] / 1e6, "_color": o.color.cpu()})
            _log(f"{name} {width}x{height} N={n}: fwd {1e3 * f['median_s']:.0f} ms, fwd+bwd {1e3 * fb['median_s']:.0f} ms")
    fw, fh, fn = FLOOR_CASE
    floor_scene = make_scene(fn, fw, fh)
    for name in backends:
        use_backend(name, device)
        f, fb = _floor(floor_scene, 10 if quick else 50)
        o = _ours(floor_scene, False, count=True)
        rows.append({"backend": name, "image": f"{fw}x{fh} (floor)", "N": fn, "visible": int((o.radii > 0).sum()),
                     "pairs_M": int(o.n_touched.sum()) / 1e6, "fwd_ms": 1e3 * f["median_s"],
                     "fwd_bwd_ms": 1e3 * fb["median_s"], "fwd_cpu_ms": 1e3 * f["cpu_s"],
                     "fwd_bwd_cpu_ms": 1e3 * fb["cpu_s"]})
        _log(f"{name} floor {fw}x{fh} N={fn}: fwd {1e3 * f['median_s']:.2f} ms, fwd+bwd {1e3 * fb['median_s']:.2f} ms")
        roof[name].append(fma_gflops(use_backend(name, device), device))
    for row in rows:
        gf = sorted(roof[row["backend"]])[len(roof[row["backend"]]) // 2]
        row["roofline_gflops"] = gf
        if "Mpairs_per_s_fwd" in row:
            row["roofline_frac_fwd"] = row["Mpairs_per_s_fwd"] * 1e6 * FLOPS_PER_PAIR_FWD / (gf * 1e9)
            row["roofline_frac_fwd_bwd"] = (row["Mpairs_per_s_fwd_bwd"] * 1e6 * (FLOPS_PER_PAIR_FWD + FLOPS_PER_PAIR_BWD)
                                            / (gf * 1e9))
        # the fastest forward+backward the counted arithmetic allows at 100 % of the measured (scalar) roofline
        row["roofline_bound_fwd_bwd_ms"] = (1e3 * row["pairs_M"] * 1e6 * (FLOPS_PER_PAIR_FWD + FLOPS_PER_PAIR_BWD)
                                            / (gf * 1e9))
    use_backend(backends[0], device)
    by_case = {(r["backend"], r["image"], r["N"]): r for r in rows}
    for row in rows:  # the vector kernels against the scalar ones, and Taichi against Warp: same run, same scene
        peer = by_case.get(({"warp": SCALAR_PEER, "taichi": TAICHI_SCALAR_PEER}.get(row["backend"]), row["image"],
                            row["N"]))
        if peer is not None:
            row["vs_scalar_fwd"] = peer["fwd_ms"] / row["fwd_ms"]
            row["vs_scalar_fwd_bwd"] = peer["fwd_bwd_ms"] / row["fwd_bwd_ms"]
        warp = by_case.get(("warp", row["image"], row["N"]))
        if row["backend"] == "taichi" and warp is not None:
            row["taichi_over_warp_fwd"] = row["fwd_ms"] / warp["fwd_ms"]
            row["taichi_over_warp_fwd_bwd"] = row["fwd_bwd_ms"] / warp["fwd_bwd_ms"]
    skipped = []
    start = time.perf_counter()
    for width, height, n in cases if device == "cpu" else []:  # the peer is written for the CPU
        if n > PEER_MAX_N or time.perf_counter() - start > PEER_BUDGET_S:
            skipped.append(f"{width}x{height} N={n}")
            continue
        scene = make_scene(n, width, height)
        peer_f = time_fn(lambda: _peer(scene, False), repeat=1, warmup=0)
        peer_fb = time_fn(lambda: _peer(scene, True), repeat=1, warmup=0)
        _log(f"peer {width}x{height} N={n}: fwd {peer_f['median_s']:.1f} s, fwd+bwd {peer_fb['median_s']:.1f} s")
        ref = _peer(scene, False)
        for row in rows:
            if (row["image"], row["N"]) == (f"{width}x{height}", n):
                row.update(peer_fwd_ms=1e3 * peer_f["median_s"], peer_fwd_bwd_ms=1e3 * peer_fb["median_s"],
                           speedup_fwd=peer_f["median_s"] * 1e3 / row["fwd_ms"],
                           speedup_fwd_bwd=peer_fb["median_s"] * 1e3 / row["fwd_bwd_ms"])
                notes.append(f"{row['backend']} {width}x{height} N={n}: max |colour - peer colour| = "
                             f"{(row['_color'] - ref).abs().max().item():.2e}")
    for row in rows:
        row.pop("_color", None)
    notes.append(f"load average at end: {os.getloadavg()[0]:.1f}; fwd_bwd_cpu_ms is process CPU time per "
                 "forward+backward (all threads), less sensitive to other users than wall time")
    notes += [
        "pairs_M: Gaussian-pixel pairs composited (sum of n_touched, after culling, the 1/255 skip and the 1e-4 stop); "
        "Mpairs_per_s_* = pairs / median time.",
        f"roofline_gflops: perf/roofline.py's FMA loop on the same backend in this run (median of before and after "
        f"the cases); roofline_frac_fwd = Mpairs/s x {FLOPS_PER_PAIR_FWD} flops / roofline, roofline_frac_fwd_bwd "
        f"uses {FLOPS_PER_PAIR_FWD} + {FLOPS_PER_PAIR_BWD} flops per pair. Both are measured under the same load, "
        "so the fraction is less sensitive to other users than the times. roofline_bound_fwd_bwd_ms = pairs x "
        f"{FLOPS_PER_PAIR_FWD + FLOPS_PER_PAIR_BWD} flops / roofline: forward+backward compositing at 100 % of that "
        "roofline (projection, binning and launches not counted), the floor under any scalar-code speed-up.",
        f"floor row ({fw}x{fh}, {fn} Gaussians): kernels.rasterize alone, forward without autograd and forward + "
        "backward from fixed upstream gradients (no loss ops), median of repeated calls; fwd_cpu_ms / "
        "fwd_bwd_cpu_ms there: process CPU time per call (on a busy machine the wall time of a ~1 ms call is mostly "
        "waiting for a core).",
        "peer: perf/raster.py torch_tiles_rasterize (tile-based vectorised torch, autograd backward), one timed run "
        "each (forward without autograd, then forward+backward), same process and scene; ours: median of repeats "
        "after one warm-up; loss = sum(colour) + 0.1 sum(depth) + sum(alpha).",
        "Warp on the CPU: tile chunks launched from kernels/_warp/launch.py's thread pool (each launch runs on one "
        "OS thread and releases the GIL); Taichi parallelises the tile loop itself (spread over n_tiles * "
        "kernels._taichi.launch.SPREAD iterations, since Taichi makes CPU tasks of >= 512 iterations).",
        f"{SCALAR_PEER}: Warp with its own compositing, projection and binning kernels (kernels/_warp/raster.py, "
        "project.py and sort.py, the CUDA kernels, scalar code on the CPU; perf.common.use_backend sets the "
        "switches); warp composites and projects with kernels/_warp/raster_cpu.py's and project_cpu.py's vector "
        "code and bins with sort_cpu.py's native code. vs_scalar_* = warp-scalar time / warp time, same run and "
        "scene.",
        f"{TAICHI_SCALAR_PEER}: Taichi compositing one pixel at a time (kernels/_taichi/raster.py, its GPU kernels); "
        "taichi composites with kernels/_taichi/raster_cpu.py's row-vector kernels; vs_scalar_* for taichi = "
        "taichi-scalar time / taichi time. taichi_over_warp_* = taichi time / warp time, same run and scene (the "
        "target: within 2x).",
        "Timed calls are made as the pipeline makes them, kernels.rasterize(count_touched=False) (the "
        "default count_touched=True costs Taichi's vector forward ~1.7x); pairs_M comes from "
        "one more call that counts.",
    ]
    if skipped:
        notes.append(f"peer not run (N > {PEER_MAX_N} or past the {PEER_BUDGET_S:.0f} s peer budget): "
                     + ", ".join(skipped))
    columns = ["backend", "image", "N", "visible", "pairs_M", "fwd_ms", "fwd_bwd_ms", "fwd_cpu_ms", "fwd_bwd_cpu_ms",
               "Mpairs_per_s_fwd", "Mpairs_per_s_fwd_bwd", "roofline_gflops", "roofline_frac_fwd",
               "roofline_frac_fwd_bwd", "roofline_bound_fwd_bwd_ms", "vs_scalar_fwd", "vs_scalar_fwd_bwd",
               "taichi_over_warp_fwd", "taichi_over_warp_fwd_bwd"]
    if device == "cpu":
        columns += ["peer_fwd_ms", "peer_fwd_bwd_ms", "speedup_fwd", "speedup_fwd_bwd"]
    return {"rows": rows, "columns": columns, "notes": notes}
