"""The plumbing probe: y <- a * x + y, to show the backend compiles and launches on the chosen device."""

import taichi as ti
import torch


# GPU: one element per thread, 128 per block / workgroup.
@ti.kernel
def _axpy(a: ti.f32, x: ti.types.ndarray(dtype=ti.f32, ndim=1), y: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in range(x.shape[0]):
        y[i] = a * x[i] + y[i]


def axpy(a: float, x: torch.Tensor, y: torch.Tensor, device: str) -> torch.Tensor:
    _axpy(float(a), x, y)
    if device != "cpu":
        ti.sync()
    return y
