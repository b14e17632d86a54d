"""perf subject "slam": one agent's throughput (frames per second) on a generated sequence at 320x240 and
640x480 per backend, with the time split between tracking, mapping and loop closure.

The default SlamConfig tracks in two stages (coarse odometry, then frame-to-model refinement); the peer is the
same pipeline with the coarse stage only (tracking.refine false), run in the same process: the tracking-time
ratio says what the refinement costs here (budget: <= 1.5x), the two ATEs what it gains.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

DESCRIPTION = "GRAND-SLAM agent throughput (fps) at 320x240 and 640x480, time split tracking / mapping / loop closure"


def _dataset(root: Path, width: int, frames: int) -> Path:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate
    from swarmsplat.slam.synthetic.config import ColorNoiseConfig, DepthNoiseConfig

    cfg = GeneratorConfig.build(name=f"perf_{width}", agents=1, frames=frames, width=width, height=width * 3 // 4,
                                depth_noise=DepthNoiseConfig(enabled=False), color_noise=ColorNoiseConfig(enabled=False))
    ds = generate(root / f"w{width}", cfg)
    return next(p for p in sorted(ds.iterdir()) if p.is_dir())


def _run(seq: Path, out: Path, backend: str, device: str, width: int, refine: bool) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import run_sequence

    cfg = SlamConfig().override({"image": {"max_width": width}, "tracking": {"refine": refine},
                                 "kernels": {"backend": backend, "device": device}})
    t0 = time.perf_counter()
    m = run_sequence(seq, out, cfg, progress=False)
    m["wall_s"] = time.perf_counter() - t0
    return m


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    frames = 6 if quick else 20
    widths = [320] if quick else [320, 640]
    rows = []
    with tempfile.TemporaryDirectory(prefix="perf_slam_") as tmp:
        root = Path(tmp)
        seqs = {w: _dataset(root, w, frames) for w in widths}
        for w in widths:
            for b in backends:
                base = _run(seqs[w], root / f"o_{b}_{w}", b, device, w, False)
                two = _run(seqs[w], root / f"p_{b}_{w}", b, device, w, True)
                t, t2 = base["time_s"], two["time_s"]
                cm = lambda m: 100 * m["ate_rmse"] if m["ate_rmse"] is not None else None  # noqa: E731
                rows.append({
                    "backend": b, "input": f"{w}x{w * 3 // 4}", "frames": frames, "fps": base["fps"],
                    "tracking_s": t["tracking"], "mapping_s": t["mapping"], "loop_closure_s": t["loop_closure"],
                    "ate_cm": cm(base), "psnr_db": base["psnr"], "gaussians": base["gaussians"],
                    "fps_two_stage": two["fps"], "tracking_s_two_stage": t2["tracking"], "ate_cm_two_stage": cm(two),
                    "ratio_time_two_stage": base["fps"] / two["fps"] if two["fps"] else None,
                    "ratio_tracking_two_stage": t2["tracking"] / t["tracking"] if t["tracking"] else None,
                })
    return {
        "rows": rows,
        "columns": ["backend", "input", "frames", "fps", "tracking_s", "mapping_s", "loop_closure_s", "ate_cm",
                    "psnr_db", "gaussians", "fps_two_stage", "tracking_s_two_stage", "ate_cm_two_stage",
                    "ratio_time_two_stage", "ratio_tracking_two_stage"],
        "notes": [
            "Generated single-agent sequence (noiseless depth), default SlamConfig (coarse RGB-D odometry tracking "
            "at 320 px) with image.max_width set to the input width and tracking.refine false; mapping renders at "
            "the working resolution (mapping.max_width 0).",
            "'two_stage' is the same run with the frame-to-model refinement on (tracking.refine, the default: "
            "Gauss-Newton against the model view at tracking.refine_max_width), in the same process; "
            "ratio_time_two_stage = fps / fps_two_stage, ratio_tracking_two_stage = tracking_s_two_stage / "
            "tracking_s.",
            "fps counts every input frame over the whole wall time (tracking + mapping + loop closure + I/O).",
        ],
    }
