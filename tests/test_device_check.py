"""The device self-check (kernels.selfcheck): a working pair passes at a working size; a device that loads but
computes wrongly, or whose driver fails, stops `swarmsplat run` before the first frame with one line naming the
backend, the device and what differed (non-zero exit, no 'complete' run); `swarmsplat devices` shows the same
check. The wrong devices are real kernels made wrong: Warp's binning losing every other tile's list, and Taichi's
old one-thread binning on Vulkan (cut short by the software driver's loop limit)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from swarmsplat import kernels
from swarmsplat.kernels import selfcheck
from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig

VULKAN = kernels.Backend("taichi", "vulkan")
QUICK = {"image": {"max_width": 160}, "tracking": {"iterations": 4, "refine_max_width": 80, "pyramid_levels": 1,
                                                    "coarse_max_width": 160},
         "mapping": {"max_width": 80, "iterations": 4, "first_iterations": 8, "seed_stride": 2},
         "submaps": {"keep_keyframe_width": 80}}


@pytest.fixture
def fresh(monkeypatch):
    """Forget which pairs passed in this process, so the check runs again."""
    monkeypatch.setattr(selfcheck, "_passed", set())


def _sequence(tmp_path: Path) -> tuple[Path, str]:
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    seq = generate(tmp_path / "data", GeneratorConfig.preset("tiny", agents=1, frames=3, seed=1)) / "agent_0"
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(SlamConfig().override(QUICK).to_yaml())
    return seq, str(cfg)


def _lose_every_other_tile(monkeypatch):
    """Warp's CPU binning, then every other tile's list emptied (its entries moved to the next tile's start)."""
    from swarmsplat.kernels._warp import sort

    real = sort.bin_tiles

    def broken(proj_bits, ntiles, rect, n, tiles_x, n_tiles, status, emit_start, scratch, tile_start, *rest):
        real(proj_bits, ntiles, rect, n, tiles_x, n_tiles, status, emit_start, scratch, tile_start, *rest)
        tile_start[1:-1:2] = tile_start[2::2][: len(tile_start[1:-1:2])]

    monkeypatch.setattr(sort, "bin_tiles", broken)


@pytest.mark.parametrize("pair", [("warp", "cpu"), ("taichi", "cpu"), ("taichi", "vulkan")])
def test_a_working_pair_passes_at_a_working_size(fresh, pair):
    if kernels.Backend(*pair) not in kernels.devices():
        pytest.skip(f"{pair[0]}-{pair[1]} does not load here")
    before = kernels.use("warp", "cpu")
    r = selfcheck.self_check(*pair, 272, 200)  # ragged tiles
    assert r.ok, r.line()
    assert kernels.active() == before
    selfcheck.require(*pair, 272, 200)  # no error, and remembered
    assert (*pair, 272, 200) in selfcheck._passed


def test_a_wrong_device_stops_the_run_before_the_first_frame(fresh, monkeypatch, tmp_path, capsys):
    seq, cfg = _sequence(tmp_path)
    _lose_every_other_tile(monkeypatch)
    code = main(["run", str(seq), "--out", str(tmp_path / "out"), "--config", cfg, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == kernels.DeviceCheckError.exit_code != 0
    assert len(err) == 1 and "self-check failed: warp-cpu at 160x120" in err[0] and "differs" in err[0], err
    assert not (tmp_path / "out" / "metrics.json").exists()  # nothing ran, nothing claims to be a result


def test_a_driver_failure_is_one_line(fresh, monkeypatch):
    from swarmsplat.kernels._warp import raster

    def fail(*args, **kw):
        raise RuntimeError("Dispatch error : RhiResult(not_supported)\n  at a line of the driver")

    monkeypatch.setattr(raster, "render_forward", fail)
    with pytest.raises(kernels.DeviceCheckError) as e:
        selfcheck.require("warp", "cpu", 64, 48)
    msg = str(e.value)
    assert "\n" not in msg and "warp-cpu at 64x48" in msg and "RuntimeError: Dispatch error" in msg


def test_taichi_one_thread_binning_on_vulkan_is_refused(fresh, monkeypatch, tmp_path, capsys):
    """What `swarmsplat run --kernels taichi --device vulkan` did before the GPU binning: an empty map reported as
    complete. With that binning put back, the run refuses to start."""
    if VULKAN not in kernels.devices():
        pytest.skip("no Vulkan driver loads on this machine")
    from swarmsplat.kernels._taichi import sort

    monkeypatch.setattr(sort, "on_cpu", lambda: True)  # the serial CPU kernel, on the GPU arch
    r = selfcheck.self_check("taichi", "vulkan", 540, 360)
    assert not r.ok and "differs from the twin" in r.detail, r.line()
    seq, cfg = _sequence(tmp_path)
    monkeypatch.setattr(selfcheck, "require", lambda b, d, w, h, real=selfcheck.require: real(b, d, 540, 360))
    code = main(["run", str(seq), "--out", str(tmp_path / "out"), "--config", cfg, "--quiet", "--kernels", "taichi",
                 "--device", "vulkan"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "taichi-vulkan at 540x360" in err[0], err
    assert not (tmp_path / "out" / "metrics.json").exists()
    kernels.use("warp", "cpu")


def test_devices_command_shows_the_check(fresh, monkeypatch, capsys):
    assert main(["devices", "--size", "64x48"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if not x.startswith("[Taichi]")]  # Taichi's banner
    assert lines[0].startswith("warp-cpu at 64x48: ok")
    assert len(lines) == len(kernels.devices())
    _lose_every_other_tile(monkeypatch)
    assert main(["devices", "--size", "64x48"]) == 1
    assert "warp-cpu at 64x48: FAILED" in capsys.readouterr().out
    assert main(["devices", "--size", "64by48"]) == 2


def test_devices_run_true_uses_the_check(fresh, monkeypatch):
    _lose_every_other_tile(monkeypatch)
    kernels.use("taichi", "cpu")
    try:
        ran = kernels.devices(run=True)
    finally:
        kernels.use("warp", "cpu")
    assert kernels.Backend("warp", "cpu") not in ran and kernels.Backend("taichi", "cpu") in ran


def test_the_probe_changes_no_result(fresh, tmp_path):
    """A run after the check (in this process) writes what a run in a process that never checked writes: the
    check renders its own scene on its own tensors."""
    import subprocess
    import sys

    seq, cfg = _sequence(tmp_path)
    outs = []
    for k, code in enumerate(["", "from swarmsplat.kernels import selfcheck\nselfcheck.require = lambda *a: None\n"]):
        out = tmp_path / f"out{k}"
        script = (code + "from swarmsplat.slam.cli import main\n"
                  f"raise SystemExit(main(['run', {str(seq)!r}, '--out', {str(out)!r}, '--config', {cfg!r}, "
                  "'--quiet']))\n")
        r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append(out)
    a, b = ((o / "trajectory.txt").read_text() for o in outs)
    assert a == b
    assert (outs[0] / "map.ply").read_bytes() == (outs[1] / "map.ply").read_bytes()
    assert json.loads((outs[0] / "metrics.json").read_text())["status"] == "complete"
