"""The end-to-end demo: generate the synthetic multi-agent dataset (cached), run the GRAND-SLAM team on it,
evaluate, and write the report — what `swarmsplat demo` runs.

    from swarmsplat.slam.run.demo import run_demo
    metrics = run_demo("demo_out")                 # 3 agents x 120 frames, report in demo_out/results/report.md
    metrics = run_demo("demo_out", preset="tiny")  # 2 agents x 10 frames: seconds, for tests
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

# Settings per preset on top of SlamConfig's defaults, chosen so the demo fits its time budget on a 2-core CPU.
DEMO_SETTINGS: dict[str, dict[str, Any]] = {
    # Mapping renders at the working resolution (320 px, session 7; it was 160 px): merged map 27.7 against
    # 24.0 dB at 320x240, 5.0 min (5.2 at 160 px) (README "Multi-agent team and the demo"). Fewer mapping iterations
    # than the defaults (20 / 60 against 30 / 100) keep the demo in its time budget.
    "default": {
        "mapping": {"iterations": 20, "first_iterations": 60},
        # Server-side global map refinement, 12 steps per keyframe (62 keyframes in one component). Measured in
        # session 11 on the demo's saved refinement inputs (320 px): with the decaying learning rate
        # (map_refine.lr_final_scale) 12 steps render 30.3 dB, as 20 steps did at the old constant rate (20 with
        # the decay: 30.8 dB, 8: 30.0 dB); 40 % less refinement time.
        "map_refine": {"iterations_per_keyframe": 12, "max_iterations": 1500},
    },
    "tiny": {
        "mapping": {"iterations": 10, "first_iterations": 30},
        "keyframes": {"every": 3},
        "loop_closure": {"min_index_gap": 3},
    },
}
# Inter-agent candidates by bag of words over RootSIFT: the agents' thumbnail descriptor does not separate
# overlapping from non-overlapping views of the generated world (median similarity 0.44 for both). With a
# vocabulary trained on another world, τ_sim = 0.5 keeps ~90 % of the overlapping pairs (and ~35 % of the
# others, which geometric verification rejects).
DEMO_SERVER: dict[str, dict[str, Any]] = {"default": {"descriptor": "bow", "tau_sim": 0.5},
                                          "tiny": {"descriptor": "bow", "tau_sim": 0.5}}
RENDER_VIEWS = {"default": 8, "tiny": 4}
# Every k-th input frame: the 15 fps sequences move little per frame, and this halves the default run's CPU time.
FRAME_STRIDE = {"default": 2, "tiny": 1}


def demo_config(preset: str, kernels: str = "warp", device: str = "cpu",
                overrides: dict[str, Any] | None = None) -> SlamConfig:
    """The SlamConfig the demo uses for `preset` (its DEMO_SETTINGS, then the backend, then `overrides`)."""
    if preset not in DEMO_SETTINGS:
        raise InputError(f"unknown demo preset {preset!r}; choose one of {', '.join(DEMO_SETTINGS)}")
    cfg = SlamConfig().override(DEMO_SETTINGS[preset])
    cfg = cfg.override({"kernels": {"backend": kernels, "device": device}})
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


def run_demo(out_dir: str | Path, *, preset: str = "default", kernels: str = "warp", device: str = "cpu",
             seed: int | None = None, config: SlamConfig | None = None, server: ServerConfig | None = None,
             progress: bool = True, observer=None) -> dict:
    """Generate (or reuse) `out_dir/dataset`, run the team into `out_dir/results`, and return its metrics.

    config / server replace the demo's own settings for `preset` (their kernels section is then used as is).
    observer: handed to run_team (the live view, slam.view.live).
    """
    from .team import run_team

    out = output_dir(out_dir, "--out")
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    data = ensure_dataset(out / "dataset", preset, seed=seed, progress=progress)
    t_gen = time.perf_counter() - t0
    cfg = config or demo_config(preset, kernels, device)
    if server is None:
        settings = dict(DEMO_SERVER.get(preset, {}))
        if settings.get("descriptor", "agent") != "agent":
            settings["vocabulary"] = str(ensure_vocabulary(out / f"vocabulary_{preset}.npz", preset, seed=seed,
                                                           progress=progress))
        server = ServerConfig(**settings)
    srv = server
    metrics = run_team(data, out / "results", cfg, server=srv, progress=progress,
                       stride=FRAME_STRIDE.get(preset, 1), render_views=RENDER_VIEWS.get(preset, 8),
                       observer=observer)
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
