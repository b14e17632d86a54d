"""slam.dense.param_ops against the plain torch forms they replace: values and gradients."""

from __future__ import annotations

import pytest
import torch

from swarmsplat.kernels import use_reference
from swarmsplat.slam.dense.gaussian_map import GaussianParams
from swarmsplat.slam.dense.param_ops import activate, clamp01, isotropic_penalty


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


def _activation_case(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    log_s = torch.randn(n, 3, generator=g) * 0.7 - 3.0
    log_s[: n // 3, 1:] = log_s[: n // 3, :1]  # isotropic rows: sign 0, no penalty gradient
    logits = torch.randn(n, generator=g) * 4.0
    colors = torch.rand(n, 3, generator=g) * 1.4 - 0.2
    colors[0] = torch.tensor([0.0, 1.0, 1.2])  # on both bounds (gradient passes) and past one (it does not)
    ups = (torch.randn(n, 3, generator=g), torch.randn(n, generator=g), torch.randn(n, 3, generator=g))
    return log_s, logits, colors, ups


def _activate_and_grads(log_s, logits, colors, ups, reference: bool, iso_weight: float = 7.0):
    p = GaussianParams(torch.zeros_like(log_s), log_s.clone().requires_grad_(True), torch.zeros(len(logits), 4),
                       logits.clone().requires_grad_(True), colors.clone().requires_grad_(True))
    with use_reference(reference):
        a = activate(p)
    loss = (a.scales * ups[0]).sum() + (a.opacities * ups[1]).sum() + (a.colors * ups[2]).sum()
    if iso_weight:
        loss = loss + iso_weight * a.isotropic
    loss.backward()
    return ([t.detach() for t in (a.scales, a.opacities, a.colors, a.isotropic)],
            [p.log_scales.grad, p.logit_opacities.grad, p.colors.grad])


@pytest.mark.parametrize("mode", ["vector", "scalar"])
@pytest.mark.parametrize("n", [1, 7, 4097])  # one Gaussian, a ragged few, one past the CPU kernels' block of 4096
def test_activate_kernels_equal_the_torch_forms(backend, monkeypatch, mode, n):
    """kernels/_<backend>/activate.py against exp, sigmoid, clamp and isotropic_penalty: values, gradients into
    log-scales (scale and penalty paths), logits and colours; Warp's CPU vector and scalar kernels both."""
    if mode == "scalar" and (backend.name != "warp" or backend.device != "cpu"):
        pytest.skip("the scalar/vector switch is Warp's on the CPU")
    from swarmsplat.kernels._warp import activate as warp_activate

    monkeypatch.setattr(warp_activate, "CPU_ACTIVATE", mode)
    case = _activation_case(n, seed=n)
    (v0, g0), (v1, g1) = (_activate_and_grads(*case, reference=r) for r in (True, False))
    # Bounds in float32 roundings (eps = 2^-24; an ulp is at most 2 eps relative). Each side's exp is within 1 ulp
    # on any x86-64 CPU (glibc's expf, the kernels' own; torch's SLEEF u10 vector exp, which it uses for long
    # tensors only: n = 1, 7 agree bit for bit, 4097 by <= 2.7 eps here). So exp differs by <= 2 ulp = 4 eps;
    # sigmoid = 1 / (1 + exp(-x)) adds a rounded add and divide per side: <= 4 ulp = 8 eps. The penalty is a mean
    # of |s - row mean| over 3N terms: the scales' 4 eps, amplified <= 3x by the row's cancellation, plus torch's
    # cascade sum of up to 12291 terms (<= log2 n = 14 roundings) per side: 64 eps (1.6 measured).
    eps = 2.0**-24
    for name, a, b, rtol in zip(("scales", "opacities", "colors", "isotropic"), v1, v0,
                                (4 * eps, 8 * eps, 0.0, 64 * eps)):
        assert torch.allclose(a, b, rtol=rtol, atol=0), name
    assert torch.equal(v1[2], v0[2])  # the clamp is exact
    assert torch.allclose(g1[0], g0[0], rtol=1e-6, atol=1e-12)
    # d o / d logit = o (1 - o) cancels where o ~ 1: 1 - o inherits o's absolute error (<= 8 eps o, above) on each
    # side, so the gradients differ by <= 16 eps |upstream| o besides their relative rounding (0.65 measured).
    ups_o = case[3][1].abs() * v0[1]
    assert ((g1[1] - g0[1]).abs() <= 1e-6 * g0[1].abs() + 16 * eps * ups_o).all()
    assert torch.equal(g1[2], g0[2]) and g1[2][0, 2] == 0 and g1[2][0, 0] == case[3][2][0, 0]
    if n >= 3:
        iso_rows = slice(0, n // 3)
        assert torch.allclose(g1[0][iso_rows], case[3][0][iso_rows] * v1[0][iso_rows], rtol=1e-6)


def test_activate_without_the_penalty_or_gradients(backend):
    """No isotropic term in the loss: the scale gradient is the upstream one times s; no grad mode: values only."""
    log_s, logits, colors, ups = _activation_case(50, seed=3)
    (v, g) = _activate_and_grads(log_s, logits, colors, ups, reference=False, iso_weight=0.0)
    assert torch.allclose(g[0], ups[0] * v[0], rtol=1e-6)
    with torch.no_grad():
        p = GaussianParams(torch.zeros(50, 3), log_s, torch.zeros(50, 4), logits, colors)
        a = activate(p)
    assert not a.scales.requires_grad and torch.allclose(a.scales, torch.exp(log_s), rtol=3e-7)


def test_activate_of_no_gaussians_and_of_float64_uses_the_torch_forms():
    a = activate(GaussianParams.empty())
    assert a.scales.shape == (0, 3) and torch.isnan(a.isotropic)
    p = GaussianParams(torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 3, dtype=torch.float64),
                       torch.zeros(2, 4, dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
                       torch.full((2, 3), 2.0, dtype=torch.float64))
    a = activate(p)
    assert a.scales.dtype == torch.float64 and torch.equal(a.colors, torch.ones(2, 3, dtype=torch.float64))
    assert float(a.isotropic) == 0.0
