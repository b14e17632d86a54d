"""The plumbing probe: y <- a * x + y, to show the backend compiles and launches on the chosen device."""

import torch
import warp as wp

wp.set_module_options({"enable_backward": False})  # forward only: no adjoint kernel to compile


# GPU: one thread per element, 256 per block, 20 registers.
@wp.kernel
def _axpy(a: wp.float32, x: wp.array(dtype=wp.float32), y: wp.array(dtype=wp.float32)):
    i = wp.tid()
    y[i] = a * x[i] + y[i]


def axpy(a: float, x: torch.Tensor, y: torch.Tensor, device: str) -> torch.Tensor:
    wp.launch(_axpy, dim=x.shape[0], inputs=[float(a), wp.from_torch(x), wp.from_torch(y)], device=device)
    if device == "cuda":
        wp.synchronize_device(device)
    return y
