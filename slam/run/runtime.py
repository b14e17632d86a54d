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
    tame_allocator(cfg.malloc_mmap_threshold_kb)


def tame_allocator(threshold_kb: int) -> bool:
    """Fix glibc's mmap threshold at `threshold_kb` (mallopt M_MMAP_THRESHOLD): blocks that large are mapped on
    their own and unmapped when freed. By default glibc raises the threshold to the largest block freed so far
    (up to 32 MB), after which tensors of a few MB come from the heap, and a heap pinned by a few live blocks
    between freed ones never shrinks: a 3,000-frame generated mission grew 740 -> 920 MB over its frames that way
    and stayed at 620-700 MB with a fixed 128 kB threshold. The price is a system call and fresh zeroed pages for
    every large tensor: Redwood 211, 128 kB against glibc's rule, peak 737 against 837 MB for 127 against 91 s of
    CPU (sys 36 against 4 s). Nothing happens for 0, off Linux or glibc, or when the user set
    MALLOC_MMAP_THRESHOLD_ (glibc read it at start). Returns whether the threshold was set."""
    import os

    from swarmsplat.kernels.memory import glibc

    libc = glibc()
    if threshold_kb <= 0 or libc is None or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    return bool(libc.mallopt(-3, int(threshold_kb) * 1024))  # M_MMAP_THRESHOLD


def check_device(cfg: KernelsConfig, cameras: list, max_width: int) -> None:
    """The kernel device's self-check (kernels.selfcheck) at the run's working size — the largest of `cameras`
    after frames wider than `max_width` are downsampled (slam.dense.frames) — before the first frame: a device
    that computes wrongly stops the run with one line (DeviceCheckError) instead of mapping garbage. Once per
    process and size; it renders its own probe scene, so the run's results do not change."""
    from swarmsplat.kernels import selfcheck

    sizes = []
    for cam in cameras:
        w, h = cam.width, cam.height
        if 0 < max_width < w:
            w, h = int(max_width), max(1, int(round(h * max_width / w)))
        sizes.append((w, h))
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    selfcheck.require(cfg.backend, cfg.device, w, h)


def kernels_record(cfg: KernelsConfig) -> dict:
    """metrics.json's "kernels": the section as configured plus `torch_threads_in_effect`, the thread count torch
    actually ran with (the configured value alone once hid that team runs ignored it)."""
    return {**cfg.model_dump(), "torch_threads_in_effect": torch.get_num_threads()}


def check_not_empty(agents: list) -> None:
    """Raise SanityError when an agent that made keyframes ends with an empty map: never a 'complete' run then."""
    from swarmsplat.kernels.errors import SanityError

    for ag in agents:
        if ag.keyframes and len(ag.gmap) == 0:
            raise SanityError(f"{ag.name}: the map is empty after {len(ag.keyframes)} keyframes; not a result")


def guard_warnings(agents: list) -> dict:
    """metrics.json "warnings", only when there were any: what the pipeline's guards repaired, i.e. the Gaussians
    removed for non-finite parameters (slam.dense.mapping.mapper)."""
    dropped = sum(ag.mapper.non_finite_dropped for ag in agents)
    return {"warnings": {"non_finite_gaussians_dropped": dropped}} if dropped else {}
