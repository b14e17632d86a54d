"""The run's compute settings reach the process: `slam.run.runtime.use_kernels` sets the backend and torch's thread
count, and both pipeline entry points (`run_sequence`, `run_team`) go through it (the team once ran with torch's
default threads: its mapping and the server's refinement were ~1.3x slower than `swarmsplat run`'s)."""

from __future__ import annotations

import pytest
import torch

from swarmsplat import kernels
from swarmsplat.slam.config import KernelsConfig, SlamConfig
from swarmsplat.slam.run.runtime import kernels_record, use_kernels


@pytest.fixture
def threads_back():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def test_use_kernels_sets_backend_and_torch_threads(threads_back):
    torch.set_num_threads(2)
    use_kernels(KernelsConfig(backend="warp", device="cpu", torch_threads=1))
    assert torch.get_num_threads() == 1
    assert kernels.active().name == "warp"
    use_kernels(KernelsConfig(backend="warp", device="cpu", torch_threads=0))  # 0: torch's own count stays
    assert torch.get_num_threads() == 1


class _Stop(Exception):
    pass


@pytest.mark.parametrize("entry", ["run_sequence", "run_team"])
def test_entry_points_apply_the_kernels_section(entry, monkeypatch, tmp_path, threads_back):
    from swarmsplat.slam.run import runtime
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = generate(tmp_path / "data", GeneratorConfig.preset("tiny", seed=0, agents=1, frames=2))
    seen = []

    def fake(cfg):
        seen.append(cfg)
        raise _Stop

    monkeypatch.setattr(runtime, "use_kernels", fake)
    cfg = SlamConfig().override({"kernels": {"torch_threads": 3}})
    if entry == "run_team":
        from swarmsplat.slam.run.team import run_team as run
    else:
        from swarmsplat.slam.io.datasets import load_dataset
        from swarmsplat.slam.run.sequence import run_sequence as run

        root = load_dataset(root).agents[0]
    with pytest.raises(_Stop):
        run(root, tmp_path / "out", cfg, progress=False)
    assert [c.torch_threads for c in seen] == [3]


def test_kernels_record_says_what_torch_ran_with(threads_back):
    torch.set_num_threads(2)
    rec = kernels_record(KernelsConfig(torch_threads=1))
    assert rec["torch_threads"] == 1 and rec["torch_threads_in_effect"] == 2 and rec["backend"] == "warp"
