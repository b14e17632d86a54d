"""The end-to-end demo: generate the synthetic multi-agent dataset (cached), run the GRAND-SLAM team on it,
evaluate, and write the report — what `swarmsplat demo` runs.

    from swarmsplat.slam.run.demo import run_demo
    metrics = run_demo("demo_out")                 # 3 agents x 120 frames, report in demo_out/results/report.md
    metrics = run_demo("demo_out", preset="tiny")  # 2 agents x 10 frames: seconds, for tests

The settings are the presets configs/demo.yaml and configs/demo-tiny.yaml.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import yaml

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import output_dir

from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.team.server import ServerConfig

# `--preset` name -> the preset file in configs/ holding the demo's settings (dataset, team, mapping, server).
PRESETS = {"default": "demo", "tiny": "demo-tiny"}


def demo_config(preset: str, kernels: str | None = None, device: str | None = None,
                overrides: dict[str, Any] | None = None) -> SlamConfig:
    """The SlamConfig the demo uses for `preset` (configs/demo.yaml or demo-tiny.yaml, then the backend when
    given, then `overrides`)."""
    if preset not in PRESETS:
        raise InputError(f"unknown demo preset {preset!r}; choose one of {', '.join(PRESETS)}")
    cfg = SlamConfig.preset(PRESETS[preset])
    backend = {k: v for k, v in (("backend", kernels), ("device", device)) if v is not None}
    if backend:
        cfg = cfg.override({"kernels": backend})
    return cfg.override(overrides) if overrides else cfg


def ensure_dataset(folder: str | Path, preset: str, *, seed: int | None = None, progress: bool = True) -> Path:
    """The generated dataset for `preset` in `folder`: reused when its dataset.yaml records identical generator
    settings, (re)generated otherwise."""
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    config = GeneratorConfig.preset(preset, seed=seed)
    folder = Path(folder)
    meta = folder / "dataset.yaml"
    want = config.model_dump(mode="json")
    if meta.is_file():
        try:
            have = (yaml.safe_load(meta.read_text()) or {}).get("generator")
        except yaml.YAMLError:
            have = None
        if have == want:
            if progress:
                print(f"[demo] reusing the dataset in {folder}", file=sys.stderr)
            return folder
    from swarmsplat.slam.io.progress import bar

    with bar(config.agents * config.frames, "[demo] generate", unit="frame", enabled=progress) as b:
        return generate(folder, config, progress=b.update)


def ensure_vocabulary(path: str | Path, preset: str, *, seed: int | None = None, progress: bool = True) -> Path:
    """A bag-of-words vocabulary (RootSIFT, registration.place_recognition) for inter-agent place recognition,
    trained on views of a *different* generated world (seed + 1000) than the dataset's, so no image the team
    will see is in its training set. Reused when present."""
    from swarmsplat.registration.place_recognition import make_recognizer
    from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, camera_for, generate_world, render

    path = Path(path)
    if path.is_file():
        return path
    base = GeneratorConfig.preset(preset, seed=seed)
    config = GeneratorConfig.preset(preset, seed=base.seed + 1000)
    world = generate_world(config.seed, config.world)
    camera = camera_for(160, 120, config.hfov_deg)
    images = [render(world, T, camera)[0] for poses in agent_poses(world, config)
              for T in poses[::max(1, config.frames // 30)]]
    if progress:
        print(f"[demo] training a place-recognition vocabulary on {len(images)} views of another world",
              file=sys.stderr)
    rec = make_recognizer("bow", n_features=300, max_side=160).fit(images)
    return rec.save(path)


def run_demo(out_dir: str | Path, *, preset: str = "default", kernels: str | None = None,
             device: str | None = None, seed: int | None = None, config: SlamConfig | None = None,
             server: ServerConfig | None = None, progress: bool = True, observer=None) -> dict:
    """Generate (or reuse) `out_dir/dataset`, run the team into `out_dir/results`, and return its metrics.

    config: the whole config (default: `demo_config(preset, kernels, device)`); its `demo` section names the
    generated dataset, `team` the frame stride and evaluation views, `server` the server's settings (a bag-of-words
    descriptor without a vocabulary gets one trained on another generated world). server: replaces config.server.
    seed: the generator's seed (None: config.demo.seed, else the generator preset's).
    observer: handed to run_team (the live view, slam.view.live).
    """
    from .team import run_team

    out = output_dir(out_dir, "--out")
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    cfg = config or demo_config(preset, kernels, device)
    if server is not None:
        cfg = cfg.model_copy(update={"server": server})
    dataset = cfg.demo.dataset
    seed = cfg.demo.seed if seed is None else seed
    data = ensure_dataset(out / "dataset", dataset, seed=seed, progress=progress)
    t_gen = time.perf_counter() - t0
    if cfg.server.descriptor == "bow" and cfg.server.vocabulary is None:
        vocabulary = ensure_vocabulary(out / f"vocabulary_{dataset}.npz", dataset, seed=seed, progress=progress)
        cfg = cfg.override({"server": {"vocabulary": str(vocabulary)}})
    metrics = run_team(data, out / "results", cfg, progress=progress, observer=observer)
    metrics["demo"] = {"preset": preset, "dataset": str(data), "generate_s": t_gen,
                       "total_s": time.perf_counter() - t0, "total_cpu_s": time.process_time() - cpu0}
    if progress:
        print(_summary(metrics, out / "results"), file=sys.stderr)
    return metrics


def _summary(m: dict, results: Path) -> str:
    cm = lambda x: "n/a" if x is None else f"{100 * x:.2f} cm"  # noqa: E731
    lines = [f"[demo] done in {m['demo']['total_s']:.0f} s (CPU {m['demo']['total_cpu_s']:.0f} s)"]
    for a in m["agents"]:
        lines.append(f"[demo]   {a['name']}: ATE {cm(a.get('ate_rmse'))} (without loop closures "
                     f"{cm(a.get('ate_rmse_no_lc'))})")
    db = lambda x: "n/a" if x is None else f"{x:.2f} dB"  # noqa: E731
    lines.append(f"[demo]   merged map PSNR {db(m.get('psnr'))} on keyframes (before global refinement "
                 f"{db(m.get('psnr_before_refine'))}), {db(m.get('psnr_novel'))} on held-out frames; "
                 f"{m['loops_accepted']} loops accepted of {m['loop_candidates']} candidates")
    lines.append(f"[demo] report: {results / 'report.md'}")
    return "\n".join(lines)
