"""The one config tree: every command reads the same file (presets, --config, flags over the file), a bad file is
one error line naming the file and the field (unknown keys list the valid ones, invalid YAML names file:line), and
every run writes the config it used as config.yaml."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig, preset_names

QUICK = {  # tiny images, a handful of iterations (as tests/test_agent.py)
    "image": {"max_width": 160},
    "tracking": {"iterations": 8, "refine_max_width": 80, "pyramid_levels": 1, "coarse_max_width": 160},
    "mapping": {"max_width": 80, "iterations": 8, "first_iterations": 20, "seed_stride": 2},
    "submaps": {"keep_keyframe_width": 80},
    "map_refine": {"iterations_per_keyframe": 2},
}
SCHEDULE = "ticks: 12\nframes_per_tick: 1\nwindows:\n  - {start: 2, end: 12, robots: [0, 1]}\n"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("config")
    rgbd = generate(root / "rgbd", GeneratorConfig.preset("tiny", agents=1, frames=6, seed=1))
    mono = generate(root / "mono", GeneratorConfig.preset("tiny", agents=2, frames=6, seed=1, mono=True))
    (root / "s.yaml").write_text(SCHEDULE)
    return {"SEQ": str(rgbd / "agent_0"), "MONO": str(mono), "SCHEDULE": str(root / "s.yaml")}


def _write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


# ---- presets ------------------------------------------------------------------------------------------------------

def test_every_preset_loads_and_validates():
    names = preset_names()
    assert {"demo", "demo-tiny", "swarm", "swarm-baseline"} <= set(names)
    for name in names:
        assert isinstance(SlamConfig.preset(name), SlamConfig)
    with pytest.raises(InputError, match="unknown preset 'nope'; choose one of .*demo-tiny"):
        SlamConfig.preset("nope")


def test_demo_presets_hold_the_demo_settings():
    """configs/demo.yaml and demo-tiny.yaml are the demo's settings on top of the defaults."""
    demo = SlamConfig().override({
        "mapping": {"iterations": 20, "first_iterations": 60},
        "map_refine": {"iterations_per_keyframe": 12, "max_iterations": 1500},
        "team": {"stride": 2, "render_views": 8}, "demo": {"dataset": "default"}})
    tiny = SlamConfig().override({
        "mapping": {"iterations": 10, "first_iterations": 30}, "keyframes": {"every": 3},
        "loop_closure": {"min_index_gap": 3}, "server": {"join_min_loops": 1},
        "team": {"stride": 1, "render_views": 4}, "demo": {"dataset": "tiny"}})
    assert SlamConfig.preset("demo") == demo
    assert SlamConfig.preset("demo-tiny") == tiny


def test_swarm_section_defaults_are_the_robots_defaults():
    """SwarmConfig's defaults build exactly the NodeConfig / SolveConfig a robot had without a config."""
    from swarmsplat.slam.flocc.swarm.node import NodeConfig
    from swarmsplat.slam.run.swarm import node_config

    assert node_config(SlamConfig().swarm) == NodeConfig()
    assert SlamConfig.preset("swarm") == SlamConfig()


def test_old_agent_only_files_still_load(tmp_path):
    f = _write(tmp_path / "c.yaml", yaml.safe_dump(QUICK))
    cfg = SlamConfig.from_yaml(f)
    assert cfg.mapping.iterations == 8 and cfg.server.descriptor == "agent" and cfg.swarm.stride == 4


def test_preset_then_file_then_overrides(tmp_path):
    f = _write(tmp_path / "c.yaml", "mapping: {iterations: 7}\nteam: {render_views: 2}\n")
    cfg = SlamConfig.from_yaml(f, {"team": {"render_views": 3}}, preset="demo")
    assert cfg.mapping.iterations == 7 and cfg.mapping.first_iterations == 60  # file over preset, preset kept
    assert cfg.team.render_views == 3 and cfg.team.stride == 2 and cfg.map_refine.iterations_per_keyframe == 12


# ---- one error line, the same for every command -------------------------------------------------------------------

BAD = {  # file text, the error after "FILE"
    "section": ("bogus: {a: 1}\n", ": field 'bogus': unknown section or key; expected one of image, tracking, "
                                   "keyframes, mapping, map_refine, exposure, submaps, loop_closure, kernels, "
                                   "max_frames, server, team, swarm, pairs, demo"),
    "key": ("swarm:\n  strides: 2\n", ": field 'swarm.strides': unknown key of section 'swarm'; expected one of "
                                      "strict, place, place_checkpoint, backend, checkpoint, device, r_thr, k, "
                                      "stride, schedule,"),
    "value": ("server:\n  tau_sim: 3\n", ": field 'server.tau_sim': expected a number <= 1, got 3"),
    "choice": ("swarm: {formulation: xx}\n", ": field 'swarm.formulation': expected one of 'is', 'ss', 'base' or "
                                             "'shared', got 'xx'"),
    "type": ("tracking:\n  iterations: many\n", ": field 'tracking.iterations': expected an integer, got 'many'"),
    "yaml": ("mapping:\n  iterations: 3\n  - x\n", ":3: invalid YAML"),
    "top": ("- a\n- b\n", ": expected a mapping of config sections at the top level, got list"),
}
COMMANDS = {
    "run": "run SEQ --out NEW",
    "demo": "demo --out NEW --preset tiny",
    "swarm": "swarm MONO --out NEW",
    "robot": "robot --id 0 MONO --out NEW --start-time 0",
    "pairs": "pairs MONO --out NEW",
}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", BAD)
def test_a_bad_config_file_is_one_line_for_every_command(data, tmp_path, capsys, command, kind):
    text, expected = BAD[kind]
    f = _write(tmp_path / "bad.yaml", text)
    paths = {**data, "NEW": str(tmp_path / "new")}
    argv = [paths.get(a, a) for a in COMMANDS[command].split()] + ["--config", f]
    assert main(argv) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith(("Warp ", "[I "))]
    assert len(err) == 1, err
    assert err[0].startswith(f"swarmsplat {command}: error: {f}{expected}"), err[0]
    assert not (tmp_path / "new").exists()  # nothing runs, nothing is written


def test_a_bad_flag_value_names_the_flag(data, tmp_path, capsys):
    assert main(["swarm", data["MONO"], "--out", str(tmp_path / "o"), "--k", "-2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "swarmsplat swarm: error: --k -2.0: field 'swarm.k': expected a number > 0, got -2.0"


def test_unknown_preset_lists_the_presets(data, tmp_path, capsys):
    assert main(["run", data["SEQ"], "--out", str(tmp_path / "o"), "--preset", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("swarmsplat run: error: unknown preset 'nope'; choose one of demo, demo-tiny,"), err


# ---- commands read the file, flags override it, runs write config.yaml --------------------------------------------

def test_run_reads_the_file_and_kernels_flags_override_it(data, tmp_path):
    f = _write(tmp_path / "c.yaml", yaml.safe_dump({**QUICK, "kernels": {"backend": "taichi"}}))
    out = tmp_path / "run"
    assert main(["run", data["SEQ"], "--out", str(out), "--config", f, "--kernels", "warp", "--frames", "3",
                 "--quiet"]) == 0
    used = SlamConfig.from_yaml(out / "config.yaml")
    assert used.kernels.backend == "warp" and used.mapping.iterations == 8
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["kernels"]["backend"] == "warp"
    assert saved["verification_budget"] == {"descriptor_per_keyframe": 3, "pose_per_keyframe": 2, "tau_sim": None}


def test_team_run_reads_the_server_and_team_sections(tmp_path):
    """`swarmsplat run --split` with a server section: the server runs with it and config.yaml holds the whole
    tree (server.yaml, the older output, holds the server's section as before)."""
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    seq = generate(tmp_path / "d", GeneratorConfig.preset("tiny", agents=1, frames=8, seed=2)) / "agent_0"
    tree = {**QUICK, "server": {"tau_sim": 0.7, "top_k": 1, "inter_loops": False}, "team": {"render_views": 1}}
    f = _write(tmp_path / "c.yaml", yaml.safe_dump(tree))
    out = tmp_path / "team"
    assert main(["run", str(seq), "--out", str(out), "--config", f, "--split", "0:4,4:8", "--quiet"]) == 0
    used = SlamConfig.from_yaml(out / "config.yaml")
    assert (used.server.tau_sim, used.server.top_k, used.server.inter_loops) == (0.7, 1, False)
    server = yaml.safe_load((out / "server.yaml").read_text())
    assert server["tau_sim"] == 0.7 and server["top_k"] == 1 and server["inter_loops"] is False
    m = json.loads((out / "metrics.json").read_text())
    assert m["render_views"] <= 2 and m["loops"]["inter"]["candidates"] == 0


def test_set_reaches_any_key_after_the_file_and_is_written(tmp_path):
    """--set KEY=VALUE (YAML value, null included) overrides the file and the flags, and config.yaml holds it."""
    from swarmsplat.slam.cli.config_flags import load_config

    f = _write(tmp_path / "c.yaml", "server:\n  top_k: 5\n  tau_sim: 0.3\n")
    cfg = load_config(f, {"--kernels": ("kernels.backend", "taichi")}, sets=[
        "server.top_k=4", "server.tau_sim=null", "kernels.backend=warp", "server.descriptor=xfeat-vlad"])
    assert (cfg.server.top_k, cfg.server.tau_sim, cfg.kernels.backend, cfg.server.descriptor) == (
        4, None, "warp", "xfeat-vlad")


def test_demo_reads_the_file_over_its_preset(tmp_path):
    f = _write(tmp_path / "c.yaml", "team: {render_views: 1}\nmapping: {iterations: 4}\n")
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--preset", "tiny", "--config", f, "--quiet",
                 "--set", "server.descriptor=bow", "--set", "server.tau_sim=0.5"]) == 0
    used = SlamConfig.from_yaml(out / "results" / "config.yaml")
    assert used.mapping.iterations == 4 and used.mapping.first_iterations == 30  # file over the tiny preset
    assert used.team.render_views == 1 and used.demo.dataset == "tiny" and used.server.join_min_loops == 1
    assert (used.server.descriptor, used.server.tau_sim) == ("bow", 0.5)  # --set over both
    assert used.server.vocabulary and Path(used.server.vocabulary).is_file()  # trained for the run, recorded
    assert json.loads((out / "results" / "metrics.json").read_text())["render_views"] == 2  # 1 per agent


def test_swarm_reads_the_file_flags_override_it_and_config_yaml_is_written(data, tmp_path):
    f = _write(tmp_path / "c.yaml", f"swarm:\n  stride: 2\n  formulation: ss\n  schedule: {data['SCHEDULE']}\n")
    out = tmp_path / "file"
    assert main(["swarm", data["MONO"], "--out", str(out), "--config", f]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["formulation"] == "ss" and m["stride"] == 2 and m["schedule"]["ticks"] == 12
    used = SlamConfig.from_yaml(out / "config.yaml")
    assert used.swarm.formulation == "ss" and used.swarm.stride == 2 and used.swarm.schedule == data["SCHEDULE"]

    out = tmp_path / "flag"
    assert main(["swarm", data["MONO"], "--out", str(out), "--config", f, "--formulation", "base",
                 "--uniform-noise"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["formulation"] == "base" and m["uniform_noise"] is True and m["stride"] == 2
    used = SlamConfig.from_yaml(out / "config.yaml")
    assert used.swarm.formulation == "base" and used.swarm.uniform_noise and used.swarm.stride == 2


def test_swarm_preset(data, tmp_path):
    out = tmp_path / "baseline"
    assert main(["swarm", data["MONO"], "--out", str(out), "--preset", "swarm-baseline", "--stride", "2",
                 "--schedule", data["SCHEDULE"]]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["formulation"], m["solver"], m["uniform_noise"]) == ("base", "gnc", True)


def test_pairs_reads_the_file_flags_override_it_and_the_config_is_written(data, tmp_path):
    from swarmsplat.slam.run.pairs import config_path, metrics_path

    f = _write(tmp_path / "c.yaml", "pairs:\n  stride: 3\n  top_k: 2\n")
    out = tmp_path / "p" / "pairs.csv"
    assert main(["pairs", data["MONO"], "--out", str(out), "--config", f, "--stride", "2", "--quiet"]) == 0
    used = SlamConfig.from_yaml(config_path(out))
    assert (used.pairs.stride, used.pairs.top_k) == (2, 2) and config_path(out).name == "pairs.config.yaml"
    assert json.loads(metrics_path(out).read_text())["n_keyframes"] == 6  # 2 agents x frames 0, 2, 4


@pytest.mark.slow
def test_swarm_processes_share_one_config_and_write_it(data, tmp_path):
    """`swarm --processes`: every robot process reads out/config.yaml (schedule and vocabulary filled in) and
    the run's config.yaml is that file; the estimates hold what the in-process run's hold (keyframes, robots, loops;
the stamp's last entry is the tick it was solved at, which depends on timing)."""
    pytest.importorskip("zenoh")
    sched = _write(tmp_path / "s.yaml", SCHEDULE.replace("frames_per_tick: 1", "frames_per_tick: 1\ntick_seconds: 0.2"))
    f = _write(tmp_path / "c.yaml", f"swarm:\n  stride: 2\n  formulation: ss\n  schedule: {sched}\n")
    base = 20000 + (hash(str(tmp_path)) % 20000)
    out = tmp_path / "zenoh"
    assert main(["swarm", data["MONO"], "--out", str(out), "--config", f, "--processes", "--port-base",
                 str(base)]) == 0
    used = SlamConfig.from_yaml(out / "config.yaml")
    assert used.swarm.formulation == "ss" and used.swarm.port_base == base
    assert used.swarm.schedule == str(out / "schedule.yaml")
    assert used.swarm.place_checkpoint == str(out / "vocabulary.npz")
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == "zenoh" and m["formulation"] == "ss"
    inproc = tmp_path / "inproc"
    assert main(["swarm", data["MONO"], "--out", str(inproc), "--config", f]) == 0
    ref = json.loads((inproc / "metrics.json").read_text())["estimate_stamp"]
    assert {k: v[:3] for k, v in ref.items()} == {k: v[:3] for k, v in m["estimate_stamp"].items()}


# ---- docs/config.md -----------------------------------------------------------------------------------------------

def test_docs_reference_is_in_sync_with_the_models():
    """docs/config.md's reference part is what `python -m swarmsplat.slam.config.reference` prints (regenerate it
    after changing a field); every field has a description, none of them a measurement log."""
    from swarmsplat.slam.config.reference import BEGIN, END, reference_markdown

    doc = (Path(__file__).resolve().parents[1] / "docs" / "config.md").read_text()
    assert BEGIN in doc and END in doc
    part = doc[doc.index(BEGIN): doc.index(END) + len(END)]
    assert part == reference_markdown(), "docs/config.md is stale: python -m swarmsplat.slam.config.reference"
    for line in part.splitlines():
        if line.startswith("| `"):
            meaning = line.rstrip(" |").rsplit(" | ", 1)[-1]
            assert meaning and not meaning.startswith("| "), line
            assert not any(w in meaning.lower() for w in ("measured", " db", "session", "readme")), line
