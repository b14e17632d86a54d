"""ICP and RGB-D registration: our Warp / Taichi kernels against Open3D (legacy and tensor) in the same process.

Scenes are renders of the synthetic room (`registration.synthetic`), two views 54 mm / 2.7 deg apart, so every
method sees the same input and the true motion is known.
"""

from __future__ import annotations

import os

import numpy as np

from .common import time_fn

DESCRIPTION = ("point-to-plane ICP per iteration and per registration on a 640x480 RGB-D pair (307k points) and on "
               "voxelised clouds, plus the coarse RGB-D stage; ours (Warp, Taichi) vs Open3D legacy / tensor")


def _err(T, T_true):
    from swarmsplat.kernels import se3

    D = se3.inverse(T_true) @ T
    return float(np.linalg.norm(D[:3, 3]) * 1e3), float(np.rad2deg(se3.rotation_angle(D[:3, :3])))


def _cpu_s(fn, repeat: int) -> float:
    """Median process CPU time (all threads) of fn: on a shared, overloaded machine wall time mostly measures
    the queue, CPU time the work done."""
    import statistics
    import time

    fn()
    times = []
    for _ in range(max(1, repeat)):
        c0 = time.process_time()
        fn()
        times.append(time.process_time() - c0)
    return statistics.median(times)


def _open3d_clouds(src, tgt, normal_radius):
    import open3d as o3d

    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.astype(np.float64)))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.astype(np.float64)))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
    ts = o3d.t.geometry.PointCloud(o3d.core.Tensor(src.astype(np.float32)))
    tt = o3d.t.geometry.PointCloud(o3d.core.Tensor(tgt.astype(np.float32)))
    tt.point.normals = o3d.core.Tensor(np.asarray(pt.normals, dtype=np.float32))
    return ps, pt, ts, tt


def _open3d_rows(label, ps, pt, ts, tt, dist, init, T_true, repeat, quick):
    """Open3D per-iteration (one ICP iteration minus one evaluation) and full registration, legacy and tensor."""
    import open3d as o3d

    reg, treg = o3d.pipelines.registration, o3d.t.pipelines.registration
    est, test = reg.TransformationEstimationPointToPlane(), treg.TransformationEstimationPointToPlane()
    crit = lambda n: reg.ICPConvergenceCriteria(1e-6, 1e-6, n)  # noqa: E731
    tcrit = lambda n: treg.ICPConvergenceCriteria(1e-6, 1e-6, n)  # noqa: E731
    init_t = o3d.core.Tensor(init)
    out = {}
    # Per iteration: the slope between 1 and 1 + k forced iterations (relative criteria 0 never stop early), so
    # the KD-tree build and the initial/final correspondence searches cancel out.
    k = 2 if quick else 4
    kt = 1 if len(ps.points) > 100_000 else k  # Open3D's tensor ICP takes ~10 s per iteration on 307k points here
    never = lambda n: reg.ICPConvergenceCriteria(0.0, 0.0, n)  # noqa: E731
    tnever = lambda n: treg.ICPConvergenceCriteria(0.0, 0.0, n)  # noqa: E731
    leg = lambda n: lambda: reg.registration_icp(ps, pt, dist, init, est, never(n))  # noqa: E731
    ten = lambda n: lambda: treg.icp(ts, tt, dist, init_t, test, tnever(n))  # noqa: E731
    r1 = 2 if quick else 3
    out["legacy_iter_s"] = max(time_fn(leg(1 + k), repeat=r1, max_seconds=30)["median_s"]
                               - time_fn(leg(1), repeat=r1, max_seconds=30)["median_s"], 1e-9) / k
    out["legacy_iter_cpu_s"] = max(_cpu_s(leg(1 + k), r1) - _cpu_s(leg(1), r1), 1e-9) / k
    out["tensor_iter_s"] = max(time_fn(ten(1 + kt), repeat=1, warmup=0, max_seconds=30)["median_s"]
                               - time_fn(ten(1), repeat=1, warmup=0, max_seconds=30)["median_s"], 1e-9) / kt
    n_full = 10 if quick else 30
    holder = {}
    full = time_fn(lambda: holder.__setitem__("r", reg.registration_icp(ps, pt, dist, init, est, crit(n_full))),
                   repeat=1 if quick else 2, warmup=0, max_seconds=60)
    out["legacy_full_s"], out["legacy_err"] = full["median_s"], _err(np.asarray(holder["r"].transformation), T_true)
    tfull = time_fn(lambda: holder.__setitem__("t", treg.icp(ts, tt, dist, init_t, test, tcrit(n_full))),
                    repeat=1 if quick else 2, warmup=0, max_seconds=60)
    out["tensor_full_s"] = tfull["median_s"]
    out["tensor_err"] = _err(holder["t"].transformation.numpy().astype(np.float64), T_true)
    return out


# The issue's reference figure: Open3D legacy point-to-plane ICP, one iteration on a full 640x480 frame, on this
# machine (the target is 30x faster than this, i.e. <= 9.3 ms, at the same accuracy).
ISSUE_LEGACY_ITER_S = 0.280


def _row(case: str, impl: str, seconds: float, peer: dict | None = None, err=None, fitness=None,
         vs_issue: bool = False) -> dict:
    """One table row; `peer` = {"legacy": s, "tensor": s} gives Open3D's times and the ratios of medians;
    `vs_issue` adds the ratio to the issue's 280 ms per legacy iteration."""
    row = {"case": case, "impl": impl, "median_ms": seconds * 1e3}
    if peer:
        row.update(open3d_legacy_ms=peer["legacy"] * 1e3, open3d_tensor_ms=peer["tensor"] * 1e3,
                   x_vs_legacy=peer["legacy"] / seconds, x_vs_tensor=peer["tensor"] / seconds)
    if vs_issue:
        row["x_vs_issue_280ms"] = ISSUE_LEGACY_ITER_S / seconds
    if err is not None:
        row.update(err_mm=err[0], err_deg=err[1])
    if fitness is not None:
        row["fitness"] = fitness
    return row


def _coarse_rows(cam, cs, ds, ct, dt, T_true, backend, repeat):
    """The coarse RGB-D stage from identity: ours (hybrid, geometric) and Open3D's odometry variants."""
    from swarmsplat import kernels
    import open3d as o3d
    from swarmsplat.registration.rgbd import rgbd_odometry

    kernels.use(backend, "cpu")
    rows = []
    for method in ("hybrid", "geometric", "open3d-intensity", "open3d-hybrid", "open3d-point-to-plane"):
        holder = {}
        t = time_fn(lambda: holder.__setitem__("r", rgbd_odometry(cs, ds, ct, dt, cam, method=method)),
                    repeat=repeat, max_seconds=20)
        r = holder["r"]
        impl = backend if method in ("hybrid", "geometric") else "open3d tensor"
        rows.append(_row(f"coarse RGB-D 640x480 from identity: {method}", impl, t["median_s"],
                         err=_err(r.T_target_source, T_true), fitness=r.fitness))
    # Open3D legacy hybrid at its defaults (the issue's 148 mm case) and with more iterations.
    K = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    rgbd = lambda c, d: o3d.geometry.RGBDImage.create_from_color_and_depth(  # noqa: E731
        o3d.geometry.Image(np.ascontiguousarray(c)), o3d.geometry.Image(np.ascontiguousarray(d)), depth_scale=1.0,
        depth_trunc=10.0, convert_rgb_to_intensity=True)
    S, Tg = rgbd(cs, ds), rgbd(ct, dt)
    odo = o3d.pipelines.odometry
    more = odo.OdometryOption(o3d.utility.IntVector([40, 20, 10]), 0.07, 0.0, 10.0)
    for name, opt in (("defaults", odo.OdometryOption()), ("40/20/10 it, depth_diff 0.07, depth_max 10", more)):
        holder = {}
        jac = odo.RGBDOdometryJacobianFromHybridTerm()
        t = time_fn(lambda: holder.__setitem__("r", odo.compute_rgbd_odometry(S, Tg, K, np.eye(4), jac, opt)),
                    repeat=1, warmup=0, max_seconds=20)
        rows.append(_row(f"coarse RGB-D 640x480 from identity: open3d-legacy-hybrid {name}", "open3d legacy",
                         t["median_s"], err=_err(np.asarray(holder["r"][1]), T_true)))
    return rows


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import torch

    from swarmsplat import kernels
    from swarmsplat.kernels import icp as K
    from swarmsplat.kernels import se3
    from swarmsplat.registration import synthetic
    from swarmsplat.registration.icp import icp_clouds, icp_rgbd
    from swarmsplat.registration.pointcloud import depth_to_points, voxel_downsample

    # Torch's intra-op threads spin against each other on a busy 2-core machine (small reductions 100x slower);
    # the kernels do the heavy work, so keep torch on one thread for the measurement and restore it after.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    load_start = os.getloadavg()
    repeat = 3 if quick else 7
    cam, (cs, ds), (ct, dt), T_true = synthetic.pair(640, 480)
    init = se3.exp(np.array([0.01, -0.01, 0.005, 0.02, 0.01, -0.02])) @ T_true  # 3 cm / 1 deg off, for every method
    rows, notes = [], []
    try:
        # Full frame as clouds for Open3D (every valid pixel: 307k points).
        src_full = depth_to_points(ds, cam)[0]
        tgt_full = depth_to_points(dt, cam)[0]
        ps, pt, ts, tt = _open3d_clouds(src_full, tgt_full, 0.05)
        o3_full = _open3d_rows("full", ps, pt, ts, tt, 0.05, init, T_true, 2 if quick else 3, quick)
        vox = 0.02
        src_v, tgt_v = voxel_downsample(src_full, vox)[0], voxel_downsample(tgt_full, vox)[0]
        psv, ptv, tsv, ttv = _open3d_clouds(src_v, tgt_v, 2.5 * vox)
        o3_vox = _open3d_rows("voxel", psv, ptv, tsv, ttv, 2 * vox, init, T_true, repeat, quick)
        tgt_normals_v = np.asarray(ptv.normals, dtype=np.float32)

        for b in backends:
            be = kernels.use(b, device)
            dev = be.torch_device
            tv, tn = K.vertices_normals_from_depth(torch.from_numpy(dt).to(dev), cam)
            sv, sn = K.vertices_normals_from_depth(torch.from_numpy(ds).to(dev), cam)
            src, srcn = sv.reshape(-1, 3).contiguous(), sn.reshape(-1, 3).contiguous()
            Tt = torch.from_numpy(init).to(dev)
            def step():
                return K.projective_normal_equations(src, Tt, tv, tn, cam, max_distance=0.05, source_normals=srcn,
                                                     max_angle_deg=45.0, robust="huber", robust_scale=0.025,
                                                     validate=False)

            full_peer = {"legacy": o3_full["legacy_iter_s"], "tensor": o3_full["tensor_iter_s"]}
            t = time_fn(step, repeat=repeat * 3, device=device)
            rows.append(_row("projective ICP iteration, 640x480 (307k pts)", b, t["median_s"], full_peer,
                             vs_issue=True))
            cpu = _cpu_s(step, repeat * 3)
            rows.append({"case": "projective ICP iteration, 640x480: process CPU time (all threads)", "impl": b,
                         "median_ms": cpu * 1e3, "open3d_legacy_ms": o3_full["legacy_iter_cpu_s"] * 1e3,
                         "x_vs_legacy": o3_full["legacy_iter_cpu_s"] / cpu,
                         "x_vs_issue_280ms": ISSUE_LEGACY_ITER_S / cpu})
            t = time_fn(lambda: K.vertices_normals_from_depth(torch.from_numpy(dt).to(dev), cam), repeat=repeat,
                        device=device)
            rows.append(_row("vertex + normal maps, 640x480", b, t["median_s"]))
            holder = {}
            t = time_fn(lambda: holder.__setitem__("r", icp_rgbd(ds, dt, cam, init)), repeat=repeat, device=device)
            rows.append(_row("full projective ICP 640x480 (8/4/2/1, 10 it/level)", b, t["median_s"],
                             {"legacy": o3_full["legacy_full_s"], "tensor": o3_full["tensor_full_s"]},
                             _err(holder["r"].T_target_source, T_true), holder["r"].fitness))
            # Voxelised clouds, nearest-neighbour association through the grid.
            s_t = torch.from_numpy(src_v).to(dev)
            g_t = torch.from_numpy(tgt_v).to(dev)
            n_t = torch.from_numpy(tgt_normals_v).to(dev)
            grid = K.PointGrid(g_t, 2 * vox)

            def nn_step():
                idx = K.associate_nearest(s_t, Tt, grid, max_distance=2 * vox, validate=False)
                return K.reduce_point_to_plane(s_t, Tt, g_t, n_t, idx, validate=False)

            t = time_fn(nn_step, repeat=repeat * 3, device=device)
            rows.append(_row(f"NN ICP iteration, voxel {vox} m ({len(src_v)} pts)", b, t["median_s"],
                             {"legacy": o3_vox["legacy_iter_s"], "tensor": o3_vox["tensor_iter_s"]}))

            def nn_full():
                holder["c"] = icp_clouds(src_v, tgt_v, init, max_distance=2 * vox, target_normals=tgt_normals_v,
                                         max_iterations=10 if quick else 30)

            t = time_fn(nn_full, repeat=repeat, device=device)
            rows.append(_row(f"full NN ICP, voxel {vox} m", b, t["median_s"],
                             {"legacy": o3_vox["legacy_full_s"], "tensor": o3_vox["tensor_full_s"]},
                             _err(holder["c"].T_target_source, T_true), holder["c"].fitness))
        for impl in ("legacy", "tensor"):
            rows.append(_row("full ICP 640x480 (307k pts, from the same init)", f"open3d {impl}",
                             o3_full[f"{impl}_full_s"], err=o3_full[f"{impl}_err"]))
        rows += _coarse_rows(cam, cs, ds, ct, dt, T_true, backends[0], 1 if quick else 2)
    finally:
        torch.set_num_threads(threads)
    load_end = os.getloadavg()
    notes += [
        f"Load average (1/5/15 min) at the start {load_start[0]:.2f}/{load_start[1]:.2f}/{load_start[2]:.2f}, at the "
        f"end {load_end[0]:.2f}/{load_end[1]:.2f}/{load_end[2]:.2f} on {os.cpu_count()} cores: on a shared machine "
        "compare against the peer in the same run and the CPU-time row.",
        "x_vs_legacy: Open3D legacy in the same process (this run); x_vs_issue_280ms: the issue's 280 ms per legacy "
        "iteration on this machine (target: 30x, i.e. <= 9.3 ms per iteration).",
        "Pair: synthetic room, 640x480, 54 mm / 2.7 deg apart; ICP rows start from the same guess 3 cm / 1 deg off.",
        "Open3D per iteration = (time of 1+k forced iterations - time of 1) / k, so tree building and the first "
        "and last searches cancel; its cloud is every valid pixel (307k) with normals from a 5 cm / 30-NN search.",
        "Ours per iteration = one fused projective association + point-to-plane reduction (Huber): float32 sums "
        "over runs of 64 points, flushed into float64.",
        "The 'process CPU time' row compares work (CPU seconds summed over threads), which a busy machine distorts "
        "less than wall time.",
        "torch is held to 1 thread during the run. Warp's CPU backend runs a launch on one thread, so our Warp "
        "wrapper cuts each launch into one part per core, launched from its own Python thread (the GIL is released "
        "during a launch); Taichi runs its outer loop on all cores itself.",
        "Coarse rows start from identity; 'hybrid' is our default coarse stage (point-to-plane + intensity, weight 0.3).",
    ]
    columns = ["case", "impl", "median_ms", "open3d_legacy_ms", "open3d_tensor_ms", "x_vs_legacy", "x_vs_tensor",
               "x_vs_issue_280ms", "err_mm", "err_deg", "fitness"]
    return {"rows": rows, "columns": columns, "notes": notes}
