"""The compute settings of a run (`SlamConfig.kernels`) applied to the process: the kernel backend and device, and
torch's intra-op thread count.

Every entry point that runs the pipeline (`slam.run.sequence.run_sequence`, `slam.run.team.run_team`) calls `use_kernels`
first. Torch's thread count matters on the CPU: the torch operations around the kernels are small (one mapping
step's activations, medians and Adam over 60k-200k Gaussians), and with torch's default of one thread per core
each of them is a thread hand-off. Measured on the demo's merged-map refinement (211k Gaussians, 62 keyframes,
2 cores): 56 ms per step with one thread against 75 ms with two.
"""

from __future__ import annotations

import torch

from swarmsplat.slam.config import KernelsConfig


def use_kernels(cfg: KernelsConfig) -> None:
    """kernels.use(cfg.backend, cfg.device) and torch.set_num_threads(cfg.torch_threads) (0 leaves torch's own
    count). Raises kernels.errors.InputError / BackendUnavailable as kernels.use does."""
    from swarmsplat import kernels

    kernels.use(cfg.backend, cfg.device)
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)


def kernels_record(cfg: KernelsConfig) -> dict:
    """metrics.json's "kernels": the section as configured plus `torch_threads_in_effect`, the thread count torch
    actually ran with (the configured value alone once hid that team runs ignored it)."""
    return {**cfg.model_dump(), "torch_threads_in_effect": torch.get_num_threads()}
