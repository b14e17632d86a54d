"""Does Taichi's CPU code generator vectorise the compositing's per-pixel work? `python -m perf.taichi_simd [--json OUT]`

The Warp CPU compositing (kernels/_warp/raster_cpu.py) is 8-lane vector code written as a native C++ snippet;
Taichi has no native snippets, so the only way to vector code there is for Taichi's LLVM pipeline to vectorise
ordinary kernel code. This times the forward compositing's per-pixel step (power, exp, alpha, the masks, the
transmittance and weight updates, branch-free) over a 1-D array on one thread, written two ways:

- `scalar`: one pixel per loop iteration, the shape kernels/_taichi/raster.py has;
- `group8`: eight pixels per iteration, unrolled with `ti.static` into eight isomorphic chains over consecutive
  elements, the shape LLVM's SLP vectoriser turns into 8-lane instructions when it runs and succeeds;

each with Taichi's `ti.exp` and with the polynomial exp the Warp snippet uses (no library call in the loop).
Equal times mean no vectorisation: the 8-lane code would be several times faster.
"""


import argparse
import sys
import time

N = 1 << 20
REPS = 20


def _kernels():
    import taichi as ti

    f1 = ti.types.ndarray(dtype=ti.f32, ndim=1)

    @ti.func
    def poly_exp(x):
        x = ti.min(ti.max(x, -20.0), 0.0)
        n = ti.floor(x * 1.4426950408889634 + 0.5)
        r = x - n * 0.693145751953125 - n * 1.42860682030941723e-06
        p = 1.0 + r * (1.0 + r * (0.5 + r * (0.16666665459 + r * (0.041665795894 + r * 0.0083334519073))))
        return p * ti.bit_cast((ti.cast(n, ti.i32) + 127) << 23, ti.f32)

    def step(use_poly: bool):
        @ti.func
        def body(T, dx):
            power = -0.01 * dx * dx
            e = ti.exp(power)
            if ti.static(use_poly):
                e = poly_exp(power)
            a = ti.min(0.99, 0.9 * e)
            valid = (T > 0.0) & (power >= -5.0) & (a >= 1.0 / 255.0)
            return ti.select(valid, T * (1.0 - a), T), ti.select(valid, a * T, 0.0)
        return body

    out = {}
    for use_poly in (False, True):
        body = step(use_poly)

        @ti.kernel
        def scalar(T: f1, C: f1, reps: ti.i32):
            for _ in range(1):  # one serial task: one thread
                for _r in range(reps):
                    for i in range(N):
                        t, w = body(T[i], ti.cast(i & 15, ti.f32) - 7.5)
                        T[i] = t
                        C[i] += w

        @ti.kernel
        def group8(T: f1, C: f1, reps: ti.i32):
            for _ in range(1):
                for _r in range(reps):
                    for gi in range(N // 8):
                        for lane in ti.static(range(8)):
                            i = gi * 8 + lane
                            t, w = body(T[i], ti.cast(i & 15, ti.f32) - 7.5)
                            T[i] = t
                            C[i] += w

        exp_name = "polynomial exp" if use_poly else "ti.exp"
        out[f"scalar, {exp_name}"] = scalar
        out[f"group8, {exp_name}"] = group8
    return out


def run() -> dict:
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=1, log_level=ti.WARN)
    rows, ref = [], {}
    for name, k in _kernels().items():
        T, C = np.ones(N, np.float32), np.zeros(N, np.float32)
        k(T, C, 1)  # compile
        times = []
        for _ in range(3):
            T, C = np.ones(N, np.float32), np.zeros(N, np.float32)
            t0 = time.perf_counter()
            k(T, C, REPS)
            times.append(time.perf_counter() - t0)
        key = name.split(", ")[1]
        ref.setdefault(key, C)
        rows.append({"case": name, "ns_per_pixel": round(min(times) / (REPS * N) * 1e9, 3),
                     "max_diff_vs_scalar": float(np.abs(C - ref[key]).max())})
    for r in rows:
        base = next(x for x in rows if x["case"] == "scalar, " + r["case"].split(", ")[1])
        r["speedup_vs_scalar"] = round(base["ns_per_pixel"] / r["ns_per_pixel"], 3)
    return {"subject": "taichi-simd", "taichi": ti.__version__, "pixels": N, "reps": REPS, "rows": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.taichi_simd", description=__doc__.splitlines()[0])
    p.add_argument("--json", dest="json_out")
    args = p.parse_args(argv)
    res = run()
    from .common import print_and_save

    print_and_save(res, args.json_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
