"""Launch settings of the Taichi kernels that differ between the CPU and the GPU archs (CUDA, Vulkan).

Taichi reads `ti.loop_config(block_dim=...)` per arch: on the CPU it is the number of loop iterations a worker
thread takes at a time, on CUDA the threads per block, on Vulkan the invocations per workgroup. A CPU setting
such as block_dim=1 (one expensive item per grab) is one thread per block on a GPU, and Taichi 1.7 dispatches a
run-time-sized loop as 65536 threads, i.e. 65536 one-thread workgroups, which Vulkan devices may refuse
("Dispatch error : RhiResult(not_supported)"). Guard CPU-only settings with `if ti.static(on_cpu()):`.
"""

import taichi as ti


def on_cpu() -> bool:
    """True when the initialised Taichi arch is a CPU (x64 or arm64); read at kernel compile time."""
    return ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64)


# Taichi 1.7's CPU code generator overrides `ti.loop_config(block_dim=...)` with an "adaptive" block of at least
# 512 iterations per task (codegen_cpu: min(1024, max(512, n / (threads * 32)))), also when
# `cpu_block_dim_adaptive=False` is passed to ti.init (measured: no change). A loop over a few hundred tiles is then
# one task on one core (320x240: 300 tiles), and 1200 tiles are 3 tasks of 512 / 512 / 176 on 2 cores. CPU kernels
# whose items are few and costly loop over `n * SPREAD` iterations and do item it // SPREAD where it % SPREAD == 0:
# a task then holds 512 / SPREAD .. 1024 / SPREAD items (8-16), and the empty iterations cost ~1 ns each.
SPREAD = 64
