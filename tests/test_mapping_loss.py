"""The kernel mapping loss (slam.dense.render.rgbd_loss_fused) against its torch twin slam.dense.render.rgbd_loss: value and
gradients to the rendered colour and depth, with and without the alpha and inlier masks, on each backend."""

from __future__ import annotations

import pytest
import torch

from swarmsplat.kernels.raster import RenderOutput
from swarmsplat.slam.dense.render import rgbd_loss, rgbd_loss_fused

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 20, 28


def _case(seed: int):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(H, W, 3, generator=g)
    depth = 1 + 3 * torch.rand(H, W, generator=g)
    depth[torch.rand(H, W, generator=g) < 0.2] = 0.0  # invalid depth
    r_c = (color + 0.1 * torch.randn(H, W, 3, generator=g)).requires_grad_(True)
    r_d = (depth + 0.2 * torch.randn(H, W, generator=g)).requires_grad_(True)
    with torch.no_grad():
        r_c[:3] += 5.0  # outliers for the inlier rule
        r_c[5, 5, 0] = color[5, 5, 0]  # an exact zero error (sign 0)
    alpha = torch.rand(H, W, generator=g)
    alpha[0, :4] = 0.0
    return r_c, r_d, alpha, color, depth


@pytest.mark.parametrize("alpha_power, inlier_k", [(0.0, 50.0), (2.0, 3.0), (1.0, None), (0.0, 1.0)])
def test_fused_loss_equals_twin(backend, alpha_power, inlier_k):
    if backend.device != "cpu":
        pytest.skip("CPU tensors here")
    results = []
    for fn in (rgbd_loss, rgbd_loss_fused):
        r_c, r_d, alpha, color, depth = _case(4)
        out = RenderOutput(r_c, r_d, r_d, alpha, torch.zeros(0), torch.zeros(0))
        loss = fn(out, color, depth, lambda_color=0.7, alpha_power=alpha_power, inlier_k=inlier_k)
        (2.5 * loss).backward()
        results.append((loss.detach(), r_c.grad, r_d.grad))
    (l0, gc0, gd0), (l1, gc1, gd1) = results
    assert torch.allclose(l0, l1, rtol=1e-5), (l0, l1)
    assert torch.allclose(gc0, gc1, rtol=1e-5, atol=1e-9)
    assert torch.allclose(gd0, gd1, rtol=1e-5, atol=1e-9)
    if alpha_power == 0:  # binary masks: rounded exactly as autograd rounds the twin (Adam amplifies last bits)
        assert torch.equal(gc0, gc1) and torch.equal(gd0, gd1)
    assert gc1.abs().sum() > 0 and gd1.abs().sum() > 0
    if inlier_k is not None and inlier_k < 10:
        assert (gc1[:3] == 0).all()  # the outlier rows are masked out


@pytest.mark.parametrize("n", [1, 2, 7, 76800])
def test_masked_median_equals_torch_median(n):
    """masked_median (NumPy selection on the CPU) returns exactly torch.median of the selected values: the lower
    middle value for even counts, NaN when a NaN is selected, ties included."""
    from swarmsplat.slam.dense.render import masked_median

    g = torch.Generator().manual_seed(n)
    v = torch.rand(n, generator=g)
    v[: n // 3] = 0.25  # ties
    v = v[torch.randperm(n, generator=g)]
    for mask in (None, torch.rand(n, generator=g) < 0.6):
        if mask is not None and not bool(mask.any()):
            mask[0] = True
        want = (v if mask is None else v[mask]).median()
        got = masked_median(v, mask)
        assert got.dtype == want.dtype and got.shape == want.shape and bool(got == want)
    img = v.reshape(1, n)
    assert bool(masked_median(img, img > -1) == img.median())
    vn = v.clone()
    vn[n // 2] = float("nan")
    assert torch.isnan(masked_median(vn)) and torch.isnan(vn.median())
    with pytest.raises(ValueError, match="selects no value"):
        masked_median(v, torch.zeros(n, dtype=torch.bool))


@pytest.mark.parametrize("alpha_power, inlier_k", [(4.0, 3.0), (0.0, None)])
def test_warp_native_cpu_loss_equals_scalar_kernels(alpha_power, inlier_k, monkeypatch):
    """kernels/_warp/loss_cpu.py (the CPU's row loops) writes the same bits as kernels/_warp/loss.py's scalar
    kernels: loss value and both gradients, with NaN alphas, exact-zero errors and invalid depth in the frame."""
    from swarmsplat import kernels
    from swarmsplat.kernels._warp import loss as warp_loss

    kernels.use("warp", "cpu")
    results = []
    for mode in ("scalar", "native"):
        monkeypatch.setattr(warp_loss, "CPU_LOSS", mode)
        r_c, r_d, alpha, color, depth = _case(9)
        alpha[1, :2] = float("nan")
        out = RenderOutput(r_c, r_d, r_d, alpha, torch.zeros(0), torch.zeros(0))
        loss = rgbd_loss_fused(out, color, depth, lambda_color=0.9, alpha_power=alpha_power, inlier_k=inlier_k)
        (1.7 * loss).backward()
        results.append((loss.detach(), r_c.grad, r_d.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b), (a, b)
    assert results[1][1].abs().sum() > 0 and results[1][2].abs().sum() > 0
