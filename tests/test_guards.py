"""The pipeline's sanity guards: a kernel device that renders nothing, or a mapping step that leaves a new submap
empty, ends the run with an error (status "failed", non-zero exit), never a "complete" run with an empty map;
Gaussians whose parameters went NaN are removed with a warning and counted in metrics.json. The device
self-check is switched off here, as if the device passed it and went wrong later."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from swarmsplat.kernels import selfcheck
from swarmsplat.kernels.errors import SanityError
from swarmsplat.slam.cli import main
from swarmsplat.slam.config import SlamConfig
from swarmsplat.slam.dense.mapping import mapper

QUICK = {"image": {"max_width": 160}, "tracking": {"iterations": 4, "refine_max_width": 80, "pyramid_levels": 1,
                                                    "coarse_max_width": 160},
         "mapping": {"max_width": 80, "iterations": 4, "first_iterations": 8, "seed_stride": 2},
         "submaps": {"keep_keyframe_width": 80}, "keyframes": {"every": 2}}


@pytest.fixture
def run(tmp_path, monkeypatch):
    """run(frames) -> (exit code, metrics.json) of `swarmsplat run` on a tiny generated sequence."""
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    monkeypatch.setattr(selfcheck, "require", lambda *a: None)
    cfg = tmp_path / "quick.yaml"
    cfg.write_text(SlamConfig().override(QUICK).to_yaml())

    def go(frames: int):
        seq = generate(tmp_path / "data", GeneratorConfig.preset("tiny", agents=1, frames=frames, seed=1))
        out = tmp_path / "out"
        code = main(["run", str(seq / "agent_0"), "--out", str(out), "--config", str(cfg), "--quiet"])
        return code, json.loads((out / "metrics.json").read_text())

    return go


def test_a_device_that_renders_nothing_fails_the_run(run, monkeypatch, capsys):
    from swarmsplat.kernels._warp import sort

    real = sort.bin_tiles

    def no_lists(*args):
        real(*args)
        args[9].zero_()  # tile_start: every tile's list empty, as a binning cut short on a GPU left them

    monkeypatch.setattr(sort, "bin_tiles", no_lists)
    code, m = run(3)
    assert code == SanityError.exit_code != 0
    assert m["status"] == "failed" and m["reason"].startswith("SanityError: submap 0: the render of its newest "
                                                              "keyframe is empty"), m["reason"]
    assert "error:" in capsys.readouterr().err


def test_non_finite_gaussians_are_removed_warned_and_counted(run, monkeypatch):
    real = mapper.Mapper.optimise
    calls = []

    def diverge(self, submap, keyframes, iterations, **kw):
        out = real(self, submap, keyframes, iterations, **kw)
        calls.append(1)
        if len(calls) == 2:  # the second keyframe's mapping: three Gaussians diverge
            submap.params.means[:2, 0] = float("nan")
            submap.params.colors[5, 1] = float("inf")
        return out

    monkeypatch.setattr(mapper.Mapper, "optimise", diverge)
    with pytest.warns(RuntimeWarning, match="3 Gaussians had NaN or Inf parameters"):
        code, m = run(4)
    assert code == 0 and m["status"] == "complete" and m["gaussians"] > 0
    assert m["warnings"] == {"non_finite_gaussians_dropped": 3}


def test_a_new_submap_left_empty_fails_the_run(run, monkeypatch):
    real = mapper.Mapper.optimise

    def all_nan(self, submap, keyframes, iterations, **kw):
        out = real(self, submap, keyframes, iterations, **kw)
        submap.params.means[:] = float("nan")
        return out

    monkeypatch.setattr(mapper.Mapper, "optimise", all_nan)
    with pytest.warns(RuntimeWarning):
        code, m = run(2)
    assert code != 0 and m["status"] == "failed"
    assert "without a Gaussian although its keyframe has valid depth" in m["reason"]


def test_a_clean_run_has_no_warnings_key(run):
    code, m = run(3)
    assert code == 0 and m["status"] == "complete" and "warnings" not in m and m["gaussians"] > 0


def test_drop_non_finite_keeps_the_finite_ones():
    from swarmsplat.slam.dense.gaussian_map import GaussianParams, Submap

    p = GaussianParams.from_points(torch.rand(6, 3), torch.rand(6, 3), torch.full((6,), 0.1))
    p.quats[1, 2] = float("nan")
    p.logit_opacities[4] = float("-inf")
    s = Submap.__new__(Submap)
    s.params = p
    assert mapper.drop_non_finite(s) == 2 and len(s.params) == 4
    assert torch.isfinite(torch.cat([t.reshape(4, -1) for t in s.params.tensors()], 1)).all()
