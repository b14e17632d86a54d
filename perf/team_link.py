"""The GRAND-SLAM team across processes against the same team in one process, and what crosses the link:
`python -m perf team-link [--quick] [--only demo|redwood-split] [--out-dir perf/results]`.

  demo           the `swarmsplat demo` dataset and config (3 generated agents, every 2nd of 120 frames, 320x240):
                 `swarmsplat run DATA --config demo.yaml` in one process, then with --processes and a lossless
                 link (images lossless, gaussians float32, no cull: the in-process outputs), with compact
                 Gaussians alone (link.gaussians compact, slam.dense.submap_codec's link form, no cull), and
                 with the link's defaults (compact images, compact Gaussians, culled as the server would)
  redwood-split  ../shared/data/redwood_livingroom1_211 cut in two (--split 0:106,106:), default config, the
                 same four runs

Each command runs as a user runs it, in its own process (--processes starts the agents' processes itself); the
figures are its metrics.json: team ATE, PSNR, loops, and for --processes the link's bytes per agent, per message
kind, per keyframe and per submap, against its keyframes sent raw at its input frames' size (8-bit RGB + 16-bit
depth: 0.384 MB at the demo's 320x240, 1.536 MB at Redwood's 640x480). --quick: the tiny
generated team (demo-tiny) only. Writes team-link-cpu.json / .md with commit, date, CPU and library versions.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import machine_info, markdown_table, write_results

REPO = Path(__file__).resolve().parents[1]
REDWOOD = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", REPO.parent / "shared" / "data")) / \
    "redwood_livingroom1_211"


def _demo_inputs(scratch: Path, preset: str) -> tuple[Path, Path]:
    """The demo's generated dataset and its config (with the trained vocabulary) as a YAML file."""
    from swarmsplat.slam.run.demo import demo_config, ensure_dataset, ensure_vocabulary

    cfg = demo_config(preset)
    data = ensure_dataset(scratch / "dataset", cfg.demo.dataset, progress=False)
    if cfg.server.descriptor == "bow" and cfg.server.vocabulary is None:
        vocab = ensure_vocabulary(scratch / "vocabulary.npz", cfg.demo.dataset, progress=False)
        cfg = cfg.override({"server": {"vocabulary": str(vocab)}})
    path = scratch / f"{preset}.yaml"
    path.write_text(cfg.to_yaml())
    return data, path


def _run(args: list[str], out: Path) -> dict:
    cmd = [sys.executable, "-m", "swarmsplat.slam", "run", *args, "--out", str(out), "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status):
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{err[-2000:]}")
    m = json.loads((out / "metrics.json").read_text())
    # usage: this process's children (the agents of --processes are grandchildren: counted once they are reaped)
    return {"metrics": m, "wall_s": round(wall, 1), "cpu_s": round(usage.ru_utime + usage.ru_stime, 1)}


def _same_files(a: Path, b: Path) -> dict:
    import filecmp

    out = {}
    for f in ("loops.csv", "map.ply", "pose_graph_optimized.g2o"):
        out[f] = (a / f).is_file() and (b / f).is_file() and filecmp.cmp(a / f, b / f, shallow=False)
    trajs = sorted(p.name for p in (a / "trajectories").glob("*.txt"))
    out["trajectories"] = all(filecmp.cmp(a / "trajectories" / t, b / "trajectories" / t, shallow=False)
                              for t in trajs)
    return out


def _row(case: str, mode: str, r: dict) -> dict:
    m = r["metrics"]
    row = {"case": case, "mode": mode, "wall_s": r["wall_s"], "ate_team_cm": _cm(m.get("ate_rmse_team")),
           "psnr": _r(m.get("psnr")), "loops": f"{m.get('loops_accepted')}/{m.get('loop_candidates')}",
           "joined": m.get("all_agents_joined")}
    link = m.get("link")
    if link:
        ag = list(link["agents"].values())
        row.update({"MB_per_agent": round(sum(a["bytes_total"] for a in ag) / len(ag) / 1e6, 2),
                    "kB_per_keyframe": round(sum(a["bytes_per_keyframe"] or 0 for a in ag) / len(ag) / 1e3, 1),
                    "kB_per_submap": round(sum(a["bytes_per_submap"] or 0 for a in ag) / len(ag) / 1e3, 1),
                    "pct_of_raw": round(100 * sum(a["fraction_of_raw"] or 0 for a in ag) / len(ag), 1)})
    return row


def _cm(x):
    return None if x is None else round(100 * x, 3)


def _r(x):
    return None if x is None else round(x, 2)


LOSSLESS = {"images": "lossless", "gaussians": "float32", "cull_gaussians": False}
GAUSSIANS = {"images": "lossless", "gaussians": "compact", "cull_gaussians": False}


def run_case(name: str, scratch: Path, quick: bool) -> list[dict]:
    scratch.mkdir(parents=True, exist_ok=True)
    if name == "demo":
        data, cfg = _demo_inputs(scratch, "tiny" if quick else "default")
        source = [str(data)]
    else:
        if not REDWOOD.is_dir():
            return []
        from swarmsplat.slam.config import SlamConfig

        cfg = scratch / "default.yaml"
        cfg.write_text(SlamConfig().to_yaml())
        source = [str(REDWOOD), "--split", "0:106,106:"]
    variants = [("in-process", cfg, []), ("processes lossless", _with_link(cfg, LOSSLESS, "lossless"), ["--processes"]),
                ("processes compact gaussians", _with_link(cfg, GAUSSIANS, "gaussians"), ["--processes"]),
                ("processes", cfg, ["--processes"])]
    if quick:
        variants.pop(2)
    rows, outs = [], {}
    for mode, c, extra in variants:
        out = scratch / f"{name}-{mode.replace(' ', '-')}"
        r = _run([*source, "--config", str(c), *extra], out)
        outs[mode] = out
        row = _row(name, mode, r)
        row["link"] = r["metrics"].get("link")
        rows.append(row)
        print(f"{name} {mode}: " + ", ".join(f"{k} {v}" for k, v in row.items() if k != "link"), file=sys.stderr)
    rows[1]["same_files_as_in_process"] = _same_files(outs["in-process"], outs["processes lossless"])
    for row in rows[1:]:
        if row["psnr"] is not None and rows[0]["psnr"] is not None:
            row["psnr_vs_in_process"] = round(row["psnr"] - rows[0]["psnr"], 2)
    return rows


def _with_link(cfg: Path, link: dict, name: str) -> Path:
    import yaml

    d = yaml.safe_load(cfg.read_text())
    d.setdefault("link", {}).update(link)
    out = cfg.with_name(f"{cfg.stem}-{name}.yaml")
    out.write_text(yaml.safe_dump(d, sort_keys=False))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf team-link", description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=["demo", "redwood-split"])
    p.add_argument("--quick", action="store_true", help="the tiny generated team only")
    p.add_argument("--out-dir", default=str(REPO / "perf" / "results"))
    p.add_argument("--scratch", help="keep the runs here (default: a temporary folder)")
    args = p.parse_args(argv)
    names = [args.only] if args.only else (["demo"] if args.quick else ["demo", "redwood-split"])
    report = {"machine": machine_info(), "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "quick": args.quick,
              "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(args.scratch or tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        for name in names:
            report["cases"][name] = run_case(name, scratch / name, args.quick)
    cols = ["case", "mode", "wall_s", "ate_team_cm", "psnr", "psnr_vs_in_process", "loops", "joined", "MB_per_agent",
            "kB_per_keyframe", "kB_per_submap", "pct_of_raw"]
    rows = [r for rs in report["cases"].values() for r in rs]
    md = ["# team-link: the GRAND-SLAM team in one process and across processes (Zenoh on localhost)", "",
          markdown_table([{k: r.get(k) for k in cols} for r in rows], cols), ""]
    for name, rs in report["cases"].items():
        for r in rs:
            if r.get("same_files_as_in_process"):
                md.append(f"- {name}: --processes output files identical to the in-process run's: "
                          + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in r["same_files_as_in_process"].items()))
            if r.get("link"):
                for agent, s in r["link"]["agents"].items():
                    kinds = ", ".join(f"{k} {v / 1e3:.1f} kB" for k, v in sorted(s["bytes_from_agent"].items()))
                    md.append(f"- {name} {r['mode']} {agent}: from agent {kinds}; to agent "
                              f"{sum(s['bytes_to_agent'].values()) / 1e3:.1f} kB")
    md.append("")
    md.append("pct_of_raw: all bytes an agent and the server exchanged, against sending each of its keyframes as "
              "raw RGB-D at the size of its input frames (8-bit RGB + 16-bit depth; metrics.json link "
              "raw_keyframe_bytes: 0.384 MB at 320x240, 1.536 MB at 640x480). psnr: the merged map rendered at "
              "keyframes' poses against the dataset's own frames (not the link's copies).")
    md.append("")
    md.append("processes: the link's defaults (link.images compact: JPEG colour of the mapping copy and the "
              "loop-closure copy's depth in inverse-depth steps; link.gaussians compact: the link form of "
              "slam.dense.submap_codec; link.cull_gaussians: without what the server's overlap cull drops anyway). "
              "The agents store finished submaps compact (submaps.storage, the default), so every mode sends the "
              "same Gaussian values: float32 sends their decoded values.")
    suffix = "-quick" if args.quick else ""
    out_dir = Path(args.out_dir)
    write_results(str(out_dir / f"team-link{suffix}-cpu.json"), str(out_dir / f"team-link{suffix}-cpu.md"), report,
                  "\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
