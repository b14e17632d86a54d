"""A compute roofline for the rasteriser's figures: a fused-multiply-add loop compiled by the same backend.

Each work item runs CHAINS independent chains x <- x * a + b for ITERS steps in registers (no memory traffic), so
the rate is the backend's attainable float32 FMA throughput on this CPU (both cores: Warp's launch is cut over
the cores by kernels/_warp/launch.py, Taichi parallelises the loop itself). Flops count 2 per FMA. The result is
written to an output so the loop cannot be dropped.

`fma_gflops` is the scalar roofline (one work item per thread, as the scalar kernels: neither backend's CPU code
generator vectorises across work items). `simd_gflops` is the machine's vector roofline: the same chains as
16-lane float32 vectors in a Warp native snippet compiled for the host (-march=native, 512-bit vectors where the
CPU has them: the flags of kernels/_warp/raster_cpu.py), i.e. what the CPU's vector units issue; the vector
compositing kernels are measured against it.
"""


import statistics
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


_SIMD = r"""
    typedef float v16 __attribute__((vector_size(64)));
    v16 x[8];
    for (int c = 0; c < 8; ++c)
        for (int l = 0; l < 16; ++l) x[c][l] = (float)(i * 16 + l) * 1e-9f + 0.1f * (float)c;
    for (int k = 0; k < iters; ++k)
        for (int c = 0; c < 8; ++c) x[c] = x[c] * a + b;
    v16 s = ((x[0] + x[1]) + (x[2] + x[3])) + ((x[4] + x[5]) + (x[6] + x[7]));
    float t = 0.0f;
    for (int l = 0; l < 16; ++l) t += s[l];
    return t;
"""
SIMD_LANES = 16


def _warp_simd_kernel():
    import warp as wp

    @wp.func_native(_SIMD)
    def _chains(a: float, b: float, iters: int, i: int) -> float:
        ...

    @wp.kernel(module="unique", module_options={"enable_backward": False, "cpu_compiler_flags": (
        "-march=native -mprefer-vector-width=512 -ffp-contract=fast")})
    def fma_simd(a: float, b: float, iters: int, offset: int, out: wp.array(dtype=float)):
        i = wp.tid() + offset
        out[i] = _chains(a, b, iters, i)

    return fma_simd


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
    return 2.0 * CHAINS * ITERS * ITEMS / _median_s(go, repeat) / 1e9


def _median_s(go, repeat: int) -> float:
    """Median wall seconds of go() over `repeat` calls after two untimed ones (compilation, first touch)."""
    go()
    go()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        go()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def simd_gflops(repeat: int = 5) -> float:
    """Median attainable GFLOP/s of the 16-lane FMA chains on the CPU's vector units, both cores (Warp CPU; call
    kernels.use("warp", "cpu") first)."""
    import warp as wp

    from swarmsplat.kernels._warp.launch import launch

    items = ITEMS // SIMD_LANES
    out = torch.zeros(items, dtype=torch.float32)
    if "simd" not in _KERNELS:
        _KERNELS["simd"] = _warp_simd_kernel()
    k = _KERNELS["simd"]
    arr = wp.from_torch(out, requires_grad=False)

    def go():
        launch(k, items, [0.999, 1e-4, ITERS, 0, arr], 3, "cpu", work=1 << 20)

    return 2.0 * CHAINS * SIMD_LANES * ITERS * items / _median_s(go, repeat) / 1e9
