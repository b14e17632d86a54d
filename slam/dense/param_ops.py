"""Per-Gaussian operations of every mapping step, in fewer and faster torch operations than their plain forms.

On a [N, 3] tensor torch's CPU kernels are slow wherever the inner dimension of 3 is reduced or broadcast
(`s.mean(dim=1, keepdim=True)` and `s - mean` ~0.25 and ~0.12 ms at N = 60k, one thread) and clamp's backward is
four passes (~0.7 ms there). At 320x240 with 60k Gaussians these two took ~2.3 ms of a ~34 ms mapping iteration.

- `clamp01(x)`: x.clamp(0, 1) whose backward is one multiply by the in-range mask the forward kept.
- `isotropic_penalty(s)`: mean |s - mean_row(s)| over all entries of s [N, 3], with the row sums as a matmul by
  ones(3, 3); value and gradient template both formed in the forward.
- `activate(params)`: a mapping step's per-Gaussian work in one kernel each way on the active backend
  (kernels/_<backend>/activate.py): scales = exp(log_scales), opacities = sigmoid(logits), clamp01(colors) and the
  isotropic penalty of the scales. Forward + backward at 60k Gaussians on one thread: 2.2-2.7 ms as the torch
  operations (with the two above), 0.8-0.9 ms as the kernels, autograd's bookkeeping included.

All three equal their plain forms (tests/test_param_ops.py): the same values up to float32 rounding of the row mean, the
same gradients, including 0 where an entry sits on the clamp's bounds' far side or at the row mean (sign 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


class _Clamp01(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(((x >= 0.0) & (x <= 1.0)).to(x.dtype))  # torch.clamp passes the gradient there
        return x.clamp(0.0, 1.0)

    @staticmethod
    def backward(ctx, g):
        (inside,) = ctx.saved_tensors
        return g * inside


def clamp01(x: torch.Tensor) -> torch.Tensor:
    """x.clamp(0, 1), differentiable, with a cheap backward."""
    if not x.requires_grad:
        return x.clamp(0.0, 1.0)
    return _Clamp01.apply(x)


class _Isotropic(torch.autograd.Function):
    # Row sums broadcast by a matmul with ones(3, 3): exact for the integer sums of signs, and an isotropic row
    # (three equal entries) gets d = 3 s - (s0 + s1 + s2) = 0 exactly, as the plain form's s - mean does.
    @staticmethod
    def forward(ctx, s):
        ones = torch.ones(3, 3, dtype=s.dtype, device=s.device)
        d3 = 3.0 * s - s @ ones  # 3 (s - row mean)
        sg = torch.sign(d3)
        ctx.save_for_backward(3.0 * sg - sg @ ones)  # 3 x d sum|d| / ds
        ctx.n3 = 3 * s.numel()
        return d3.abs().sum() / ctx.n3

    @staticmethod
    def backward(ctx, g):
        (template,) = ctx.saved_tensors
        return template * (g / ctx.n3)


def isotropic_penalty(s: torch.Tensor) -> torch.Tensor:
    """(s - s.mean(dim=1, keepdim=True)).abs().mean() for scales s [N, 3], N >= 1."""
    if s.dim() != 2 or s.shape[1] != 3 or s.shape[0] == 0:
        return (s - s.mean(dim=1, keepdim=True)).abs().mean()
    return _Isotropic.apply(s)


@dataclass
class Activated:
    """A GaussianParams' rasteriser inputs and its isotropic penalty, each differentiable in the params."""

    scales: torch.Tensor  # [N, 3] exp(log_scales)
    opacities: torch.Tensor  # [N] sigmoid(logit_opacities)
    colors: torch.Tensor  # [N, 3] clamp(colors, 0, 1)
    isotropic: torch.Tensor  # 0-dim: isotropic_penalty(scales)


class _Activate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, log_scales, logits, colors, impl, device):
        ls, lo, col = (t.detach().contiguous() for t in (log_scales, logits, colors))
        scales, colors01 = torch.empty_like(ls), torch.empty_like(col)
        opac, absdev = torch.empty_like(lo), torch.empty_like(lo)
        impl.forward(ls, lo, col, scales, opac, colors01, absdev, device)
        ctx.save_for_backward(scales, opac, col)
        ctx.args = (impl, device)
        ctx.n9 = 9 * lo.shape[0]  # isotropic_penalty = sum(absdev) / 3 / (3 N)
        return scales, opac, colors01, absdev.sum() / ctx.n9

    @staticmethod
    def backward(ctx, g_s, g_o, g_c, g_iso):
        scales, opac, col = (t.detach() for t in ctx.saved_tensors)  # saved outputs come back requiring grad
        impl, device = ctx.args
        d_ls, d_lo, d_col = torch.empty_like(scales), torch.empty_like(opac), torch.empty_like(col)
        k_iso = float(g_iso / ctx.n9)  # float32, as _Isotropic's template * (g / n3)
        impl.backward(scales, opac, col, g_s.contiguous(), g_o.contiguous(), g_c.contiguous(), k_iso, d_ls, d_lo,
                      d_col, device)
        return d_ls, d_lo, d_col, None, None


def activate(params) -> Activated:
    """`params`' (a GaussianParams) scales, opacities, clamp01(colors) and isotropic_penalty(scales): one kernel
    each way on the active backend for float32 params with at least one Gaussian; the plain torch forms (the
    twin) inside `kernels.use_reference()`, for other dtypes and for no Gaussians."""
    from swarmsplat.kernels import reference_active

    ls, lo, col = params.log_scales, params.logit_opacities, params.colors
    if reference_active() or len(lo) == 0 or not all(t.dtype == torch.float32 for t in (ls, lo, col)):
        s = params.scales
        return Activated(s, params.opacities, clamp01(col), isotropic_penalty(s))
    from swarmsplat import kernels

    b = kernels.active()
    return Activated(*_Activate.apply(ls, lo, col, kernels.backend_module("activate"), b.device))
