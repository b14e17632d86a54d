"""slam.param_ops against the plain torch forms they replace: values and gradients."""

from __future__ import annotations

import torch

from slam.param_ops import clamp01, isotropic_penalty


def test_clamp01_equals_torch_clamp_with_gradients():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(500, 3, generator=g) * 1.4 - 0.2
    x[:3, 0] = torch.tensor([0.0, 1.0, float("nan")])  # on the bounds (gradient passes), NaN (it does not)
    up = torch.rand(500, 3, generator=g)
    grads = []
    for f in (lambda t: t.clamp(0.0, 1.0), clamp01):
        t = x.clone().requires_grad_(True)
        y = f(t)
        (y.nan_to_num() * up).sum().backward()
        grads.append((y.detach(), t.grad))
    (y0, g0), (y1, g1) = grads
    assert torch.equal(y0.nan_to_num(), y1.nan_to_num()) and torch.isnan(y1[2, 0])
    assert torch.equal(g0, g1) and g1[0, 0] == up[0, 0] and g1[1, 0] == up[1, 0] and g1[2, 0] == 0
    assert (g1 == 0).sum() > 50
    with torch.no_grad():
        assert torch.equal(clamp01(x).nan_to_num(), y0.nan_to_num())


def test_isotropic_penalty_equals_the_plain_form():
    g = torch.Generator().manual_seed(1)
    log_s = torch.randn(1000, 3, generator=g) * 0.5 - 3.0
    log_s[0] = -2.0  # an isotropic Gaussian: every entry at its row mean (gradient 0 there)
    res = []
    for f in (lambda s: (s - s.mean(dim=1, keepdim=True)).abs().mean(), isotropic_penalty):
        t = log_s.clone().requires_grad_(True)
        val = 0.3 * f(torch.exp(t))
        val.backward()
        res.append((val.detach(), t.grad))
    (v0, g0), (v1, g1) = res
    assert torch.allclose(v1, v0, rtol=1e-6) and v0 > 0
    assert torch.allclose(g1, g0, rtol=1e-5, atol=1e-12) and not g1[0].any() and g1[1:].abs().min() > 0


def test_isotropic_penalty_of_no_gaussians_is_nan_like_the_plain_form():
    assert torch.isnan(isotropic_penalty(torch.zeros(0, 3)))
