"""Loops between views far apart, on real data, as a user runs them (`swarmsplat run ...` with the defaults):

- `hololens-split`: the HoloLens 2 office walk as two agents, frames 0-131 and 152-290 (`--split 0:132,152:`),
  whose overlapping views are typically ~4 m and ~100° apart: joined or not, team ATE under one alignment,
  each agent's ATE with and without loop closure, merged-map PSNR, loops accepted, the cloud route's work;
- `hololens-one`: the whole walk as one agent: loop candidates accepted, ATE with and without loop closure;
- `redwood-split-60` / `redwood-split-mid`: Redwood 211 as `--split 0:60,150:210` and `--split 0:106,106:`, each
  also with the cloud route off (`loop_closure.cloud_route` and `server.cloud_route` false: the named peer in the
  same run) — still joined, ATE, loop-closure seconds per keyframe and its ratio to the peer;
- `different-places`: Redwood's living room and the HoloLens office as two agents (80 frames each, every 2nd):
  zero joins expected.

- `demo`: the demo's generated team with the demo's settings, and with the cloud route off.

`--quick` runs the Redwood and the different-places cases. Needs ../shared/data (SWARMSPLAT_SHARED_DATA).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

DESCRIPTION = "wide-viewpoint loops and joins on real data (HoloLens office, Redwood splits, two different places)"

OFF = {"loop_closure": {"cloud_route": False}, "server": {"cloud_route": False}}


def _data(name: str) -> Path:
    from .common import shared_data

    return shared_data(name, "wide-joins")


def _loop_s_per_keyframe(m: dict) -> float:
    srv = m["time_s"]["server"]
    n = sum(a["keyframes"] for a in m["agents"])
    return (srv["intra"] + srv["inter"]) / n if n else float("nan")


def _team(case: str, ds, out: Path, overrides: dict | None = None, **kw) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.team import run_team

    cfg = SlamConfig().override(overrides or {})
    t0 = time.perf_counter()
    m = run_team(ds, out, cfg, progress=False, **kw)
    wall = time.perf_counter() - t0
    cloud = m["inter_verify"]["cloud_route"]
    return {"case": case, "cloud_route": bool(cfg.server.cloud_route and cfg.loop_closure.cloud_route),
            "joined": bool(m["all_agents_joined"]), "joins": m["joins"]["made"],
            "ate_team_cm": None if m["ate_rmse_team"] is None else round(100 * m["ate_rmse_team"], 2),
            "ate_agents_cm": [None if a["ate_rmse"] is None else round(100 * a["ate_rmse"], 2) for a in m["agents"]],
            "ate_agents_no_lc_cm": [None if a["ate_rmse_no_lc"] is None else round(100 * a["ate_rmse_no_lc"], 2)
                                    for a in m["agents"]],
            "psnr_merged": None if m.get("psnr") is None else round(m["psnr"], 2),
            "inter_accepted": m["loops"]["inter"]["accepted"], "inter_candidates": m["loops"]["inter"]["candidates"],
            "intra_accepted": m["loops"]["intra"]["accepted"], "intra_candidates": m["loops"]["intra"]["candidates"],
            "cloud_inter": cloud["inter"], "cloud_intra": cloud["intra"],
            "loop_s_per_keyframe": round(_loop_s_per_keyframe(m), 3), "wall_s": round(wall, 1),
            "keyframes": sum(a["keyframes"] for a in m["agents"])}


def _one(case: str, path: Path, out: Path) -> dict:
    from swarmsplat.slam.config import SlamConfig
    from swarmsplat.slam.run.sequence import run_sequence

    cfg = SlamConfig()
    t0 = time.perf_counter()
    m = run_sequence(path, out, cfg, progress=False)
    wall = time.perf_counter() - t0
    n = m["loop_candidates"]
    return {"case": case, "cloud_route": bool(cfg.loop_closure.cloud_route), "ate_cm": round(100 * m["ate_rmse"], 2),
            "ate_no_lc_cm": round(100 * m["ate_rmse_no_lc"], 2),
            "psnr_merged": None if m.get("psnr_merged") is None else round(m["psnr_merged"], 2),
            "psnr_submaps": None if m.get("psnr") is None else round(m["psnr"], 2),
            "loops_accepted": m["loops_accepted"], "loop_candidates": n,
            "accepted_fraction": round(m["loops_accepted"] / n, 3) if n else None,
            "cloud": m["loops_cloud_route"], "loop_s_per_keyframe": round(m["time_s"]["loop_closure"] /
                                                                         max(m["keyframes"], 1), 3),
            "wall_s": round(wall, 1), "keyframes": m["keyframes"]}


def _with_peer(rows: list, case: str, make_ds, out: Path, base: dict | None = None, **kw) -> None:
    """The case with the defaults (`base` on top) and with the cloud route off, and the loop-time ratio."""
    for off in (False, True):
        cfg = dict(base or {})
        if off:
            cfg.update({k: {**cfg.get(k, {}), **v} for k, v in OFF.items()})
        rows.append(_team(case, make_ds(), out / f"{case}-{'off' if off else 'on'}", cfg, **kw))
    on, peer = rows[-2], rows[-1]
    on["loop_s_ratio_to_off"] = round(on["loop_s_per_keyframe"] / max(peer["loop_s_per_keyframe"], 1e-9), 2)


def run(*, backends: list[str], device: str, quick: bool, hololens_only: bool = False) -> dict:
    """Every case (`quick`: the Redwood and two-places cases; `hololens_only`: the two HoloLens cases)."""
    from swarmsplat import kernels
    from swarmsplat.slam.io.datasets import load_dataset, load_sequence
    from swarmsplat.slam.io.datasets.split import split_sequence

    kernels.use(backends[0], device)
    rows = []
    with tempfile.TemporaryDirectory(prefix="swarmsplat-wide-") as tmp:
        tmp = Path(tmp)
        if not quick:
            holo = load_sequence(_data("hololens_office_85_378"))
            rows.append(_team("hololens-split", split_sequence(holo, [(0, 132), (152, None)]), tmp / "hs"))
            rows.append(_one("hololens-one", _data("hololens_office_85_378"), tmp / "h1"))
        if hololens_only:
            return _result(rows)
        if not quick:
            from swarmsplat.slam.run.demo import demo_config, ensure_dataset

            demo = demo_config("default")
            data = ensure_dataset(tmp / "demo-data", demo.demo.dataset, seed=demo.demo.seed, progress=False)
            _with_peer(rows, "demo", lambda: load_dataset(data), tmp, demo.model_dump(mode="json"))
        redwood = load_sequence(_data("redwood_livingroom1_211"))
        for case, ranges in (("redwood-split-60", [(0, 60), (150, 210)]), ("redwood-split-mid", [(0, 106), (106, None)])):
            _with_peer(rows, case, lambda r=ranges: split_sequence(redwood, r), tmp, render_views=4)
        root = tmp / "two-places"
        root.mkdir()
        (root / "living").symlink_to(_data("redwood_livingroom1_211"))
        (root / "office").symlink_to(_data("hololens_office_85_378"))
        (root / "dataset.yaml").write_text("name: two places\nkind: rgbd\nagents: [living, office]\n")
        rows.append(_team("different-places", load_dataset(root), tmp / "two", limits=[160, 160], stride=2,
                          render_views=2))
    return _result(rows)


def _result(rows: list) -> dict:
    cols = ["case", "cloud_route", "joined", "joins", "ate_team_cm", "ate_agents_cm", "ate_agents_no_lc_cm",
            "ate_cm", "ate_no_lc_cm", "psnr_merged", "psnr_submaps", "inter_accepted", "inter_candidates", "intra_accepted",
            "intra_candidates", "loops_accepted", "loop_candidates", "accepted_fraction", "loop_s_per_keyframe",
            "loop_s_ratio_to_off", "keyframes", "wall_s"]
    return {"rows": rows, "columns": cols,
            "notes": ["every case with the default config unless cloud_route says false (the peer: "
                      "loop_closure.cloud_route and server.cloud_route off; true: both on); loop_s_per_keyframe: the server's "
                      "(team) or the agent's (one) loop-closure seconds over the keyframes, wall clock, so a loaded "
                      "machine inflates it — compare the ratio in one run",
                      "HoloLens poses are the device's own tracking (a few mm to cm), not motion capture"]}
