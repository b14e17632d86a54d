"""The map a user sees, as `swarmsplat run` makes it with the defaults (the camera's photometric model on `auto`:
switched on by the first keyframe whose exposure departs from the map's colours), beside the same run with the
model off (`exposure.enabled` false, the named peer in the same run):

- `hololens-one`: the real HoloLens 2 office walk (../shared/data/hololens_office_85_378) as one agent;
- `redwood-211`: Redwood living room 1, 211 rendered frames with noise (../shared/data/redwood_livingroom1_211);
- `demo`: the demo's generated three-agent team with the demo's settings (`--quick` leaves it and the HoloLens
  walk out).

Per case: keyframes rendered from their own submaps (`psnr_submaps`, the mapping stage's result) and from the
merged, refined map (`psnr_merged`), their difference (`merge_loss_db`), held-out frames (`psnr_held_out`: tracked
frames that never were keyframes), the merged map's depth L1, ATE, the keyframes' exposure gains, and the wall
time. With the model on, renders are scored with each keyframe's exposure (held-out frames: interpolated from the
keyframes around them); `psnr_merged_raw` scores the colours map.ply holds (the map's colours at the keyframes'
median exposure) without each view's own; `model_from_keyframe` says where the model switched on (none: it
stayed off).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

DESCRIPTION = "merged-map quality on real and generated data, the defaults (exposure model auto) against it off"

MODES = (("auto", {"exposure": {"enabled": "auto"}}), ("off", {"exposure": {"enabled": False}}))


def _data(name: str) -> Path:
    from .common import shared_data

    return shared_data(name, "map-quality")


def _r(x, k=2):
    return None if x is None else round(float(x), k)


def _one(case: str, path: Path, out: Path, overrides: dict) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import run_sequence

    cfg = SlamConfig().override(overrides)
    t0 = time.perf_counter()
    m = run_sequence(path, out, cfg, progress=False)
    wall = time.perf_counter() - t0
    ex = m.get("exposure") or {}
    own, merged = m.get("psnr"), m.get("psnr_merged")
    return {"case": case, "exposure": cfg.exposure.enabled, "model_from_keyframe": ex.get("model_from_keyframe"),
            "psnr_submaps": _r(own), "psnr_merged": _r(merged),
            "merge_loss_db": _r(None if own is None or merged is None else own - merged),
            "psnr_held_out": _r(m.get("psnr_novel")), "psnr_merged_raw": _r(m.get("psnr_merged_raw")),
            "ssim_merged": _r(m.get("ssim_merged"), 3), "depth_l1_merged_cm": _r(100 * m["depth_l1_merged"])
            if m.get("depth_l1_merged") is not None else None,
            "ate_cm": _r(None if m.get("ate_rmse") is None else 100 * m["ate_rmse"]),
            "gain_min": _r(ex.get("gain_min"), 3), "gain_max": _r(ex.get("gain_max"), 3),
            "outlier_keyframes": ex.get("outlier_keyframes"), "keyframes": m["keyframes"], "wall_s": round(wall, 1)}


def _demo(out: Path, overrides: dict) -> dict:
    from swarmsplat.slam.io.datasets import load_dataset
    from swarmsplat.slam.run.demo import demo_config, ensure_dataset
    from swarmsplat.slam.run.team import run_team

    demo = demo_config("default", overrides=overrides)
    data = ensure_dataset(out.parent / "demo-data", demo.demo.dataset, seed=demo.demo.seed, progress=False)
    t0 = time.perf_counter()
    m = run_team(load_dataset(data), out, demo, progress=False)
    wall = time.perf_counter() - t0
    own, merged = m.get("psnr_submaps"), m.get("psnr")
    froms = [(a.get("exposure") or {}).get("model_from_keyframe") for a in m["agents"]]
    return {"case": "demo", "exposure": demo.exposure.enabled, "model_from_keyframe": froms, "psnr_submaps": _r(own),
            "psnr_merged": _r(merged), "merge_loss_db": _r(None if own is None or merged is None else own - merged),
            "psnr_held_out": _r(m.get("psnr_novel")), "psnr_merged_raw": _r(m.get("psnr_raw")),
            "ssim_merged": _r(m.get("ssim"), 3),
            "depth_l1_merged_cm": _r(None if m.get("depth_l1") is None else 100 * m["depth_l1"]),
            "ate_cm": _r(None if m.get("ate_rmse_team") is None else 100 * m["ate_rmse_team"]),
            "keyframes": sum(a["keyframes"] for a in m["agents"]), "wall_s": round(wall, 1)}


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from swarmsplat import kernels

    kernels.use(backends[0], device)
    rows = []
    with tempfile.TemporaryDirectory(prefix="swarmsplat-mapq-") as tmp:
        tmp = Path(tmp)
        for tag, over in MODES:
            if not quick:
                rows.append(_one("hololens-one", _data("hololens_office_85_378"), tmp / f"h-{tag}", over))
            rows.append(_one("redwood-211", _data("redwood_livingroom1_211"), tmp / f"r-{tag}", over))
            if not quick:
                rows.append(_demo(tmp / f"demo-{tag}", over))
    cols = ["case", "exposure", "model_from_keyframe", "psnr_submaps", "psnr_merged", "merge_loss_db", "psnr_held_out", "psnr_merged_raw",
            "ssim_merged", "depth_l1_merged_cm", "ate_cm", "gain_min", "gain_max", "outlier_keyframes", "keyframes",
            "wall_s"]
    return {"rows": rows, "columns": cols,
            "notes": ["every case with the default config and exposure.enabled set as the exposure column says (auto: the "
                      "default; false: the peer without the photometric model); PSNR in dB at the working resolution; ate_cm: the agent's (one agent) or the team's "
                      "under one alignment (demo)",
                      "HoloLens poses are the device's own tracking (a few mm to cm), not motion capture"]}
