"""A compute roofline for the rasteriser's figures: a fused-multiply-add loop compiled by the same backend.

Each work item runs CHAINS independent chains x <- x * a + b for ITERS steps in registers (no memory traffic), so
the rate is the backend's attainable float32 FMA throughput on this CPU (both cores: Warp's launch is cut over
the cores by kernels/_warp/launch.py, Taichi parallelises the loop itself). Flops count 2 per FMA. The result is
written to an output so the loop cannot be dropped.
"""


import time

import torch

CHAINS = 8
ITERS = 4096
ITEMS = 1 << 15


def _warp_kernel():
    import warp as wp

    @wp.kernel(module="unique")
    def fma_loop(a: float, b: float, iters: int, offset: int, out: wp.array(dtype=float)):
        i = wp.tid() + offset
        x0 = float(i) * 1e-9
        x1 = x0 + 0.1
        x2 = x0 + 0.2
        x3 = x0 + 0.3
        x4 = x0 + 0.4
        x5 = x0 + 0.5
        x6 = x0 + 0.6
        x7 = x0 + 0.7
        for _k in range(iters):
            x0 = x0 * a + b
            x1 = x1 * a + b
            x2 = x2 * a + b
            x3 = x3 * a + b
            x4 = x4 * a + b
            x5 = x5 * a + b
            x6 = x6 * a + b
            x7 = x7 * a + b
        out[i] = x0 + x1 + x2 + x3 + x4 + x5 + x6 + x7

    return fma_loop


def _taichi_kernel():
    import taichi as ti

    @ti.kernel
    def fma_loop(a: ti.f32, b: ti.f32, iters: ti.i32, out: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(out.shape[0]):
            x0 = ti.cast(i, ti.f32) * 1e-9
            x1 = x0 + 0.1
            x2 = x0 + 0.2
            x3 = x0 + 0.3
            x4 = x0 + 0.4
            x5 = x0 + 0.5
            x6 = x0 + 0.6
            x7 = x0 + 0.7
            for _k in range(iters):
                x0 = x0 * a + b
                x1 = x1 * a + b
                x2 = x2 * a + b
                x3 = x3 * a + b
                x4 = x4 * a + b
                x5 = x5 * a + b
                x6 = x6 * a + b
                x7 = x7 * a + b
            out[i] = x0 + x1 + x2 + x3 + x4 + x5 + x6 + x7

    return fma_loop


_KERNELS: dict = {}


def fma_gflops(backend: str, device: str = "cpu", repeat: int = 5) -> float:
    """Median attainable GFLOP/s of the FMA loop on the active backend `backend` (call kernels.use first)."""
    out = torch.zeros(ITEMS, dtype=torch.float32, device="cuda" if device == "cuda" else "cpu")
    if backend not in _KERNELS:
        _KERNELS[backend] = _warp_kernel() if backend == "warp" else _taichi_kernel()
    k = _KERNELS[backend]
    if backend == "warp":
        import warp as wp

        from swarmsplat.kernels._warp.launch import launch

        arr = wp.from_torch(out, requires_grad=False)

        def go():
            launch(k, ITEMS, [0.999, 1e-4, ITERS, 0, arr], 3, device)
            if device == "cuda":
                wp.synchronize_device(device)
    else:
        import taichi as ti

        def go():
            k(0.999, 1e-4, ITERS, out)
            ti.sync()
    go()
    go()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        go()
        times.append(time.perf_counter() - t0)
    times.sort()
    return 2.0 * CHAINS * ITERS * ITEMS / times[len(times) // 2] / 1e9
