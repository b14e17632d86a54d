import subprocess
import sys

import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels.errors import BackendError, InputError


def test_axpy_runs_on_each_backend(backend):
    x = torch.arange(1000, dtype=torch.float32, device=backend.torch_device)
    y = torch.ones(1000, dtype=torch.float32, device=backend.torch_device)
    kernels.axpy(2.5, x, y)
    assert torch.allclose(y.cpu(), 2.5 * torch.arange(1000, dtype=torch.float32) + 1)


def test_unknown_backend_and_device_are_one_line_errors():
    with pytest.raises(BackendError, match="unknown kernel backend 'cupy'"):
        kernels.use("cupy", "cpu")
    with pytest.raises(BackendError, match="unknown device 'tpu'"):
        kernels.use("warp", "tpu")


@pytest.mark.skipif(kernels.cuda_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("name", ["warp", "taichi"])
def test_cuda_without_gpu_is_a_clear_error(name):
    with pytest.raises(BackendError, match="no CUDA device"):
        kernels.use(name, "cuda")


def test_axpy_rejects_bad_arguments(backend):
    dev = backend.torch_device
    with pytest.raises(InputError, match="argument 'x': expected dtype"):
        kernels.axpy(1.0, torch.ones(3, dtype=torch.float64, device=dev), torch.ones(3, device=dev))
    with pytest.raises(InputError, match="argument 'y': expected shape"):
        kernels.axpy(1.0, torch.ones(3, device=dev), torch.ones(4, device=dev))
    with pytest.raises(InputError, match="argument 'x': contains NaN"):
        kernels.axpy(1.0, torch.tensor([1.0, float("nan")], device=dev), torch.ones(2, device=dev))


def test_import_initialises_nothing():
    code = (
        "import sys, swarmsplat.kernels, swarmsplat.slam, swarmsplat.registration, swarmsplat.graph\n"
        "import swarmsplat.kernels.backend as b\n"
        "assert b._active is None and b._taichi_arch is None and not b._warp_ready\n"
        "assert 'taichi' not in sys.modules and 'warp' not in sys.modules, [m for m in sys.modules if m in ('taichi','warp')]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
