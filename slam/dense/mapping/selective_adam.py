"""Adam over the rows (Gaussians) a step has gradients for: the server's map refinement optimises a merged map of
several hundred thousand Gaussians one keyframe at a time, and a keyframe sees a fraction of them.

torch.optim.Adam would update every row on every step: the rows out of view get a zero gradient, but their moments
decay and they keep moving along their old momentum, and the step costs the whole map (measured on the demo: most
of a refinement step). Here a step gathers, updates and scatters only the rows it is given, with a step count per
row for Adam's bias correction, so a row's update sequence is exactly Adam's over the steps that saw it (the
"selective" or sparse Adam of Gaussian-splatting trainers). Tested against torch.optim.Adam on a row that is
in every step (tests/test_selective_adam.py).
"""

from __future__ import annotations

import torch


class SelectiveAdam:
    """Adam for `params` (tensors with the same number of rows, updated in place, no autograd) with one
    learning rate each. `step(idx, grads)` applies one Adam step to the rows `idx` (unique) of every tensor."""

    def __init__(self, params: list[torch.Tensor], lrs: list[float], betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-15):
        if len(params) != len(lrs) or not params:
            raise ValueError("SelectiveAdam: one learning rate per parameter tensor")
        n = params[0].shape[0]
        if any(p.shape[0] != n for p in params):
            raise ValueError("SelectiveAdam: every parameter tensor needs the same number of rows")
        self.params = params
        self.lrs = [float(lr) for lr in lrs]
        self.b1, self.b2 = float(betas[0]), float(betas[1])
        self.eps = float(eps)
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]
        self.steps = torch.zeros(n, dtype=torch.float64)

    @torch.no_grad()
    def step(self, idx: torch.Tensor, grads: list[torch.Tensor | None]) -> None:
        """One step on rows `idx` [k] (int64, unique); grads[i] [k, ...] is the gradient of params[i][idx] (None:
        no gradient, that tensor's rows are left as they are)."""
        if idx.numel() == 0:
            return
        t = self.steps[idx] + 1.0
        self.steps[idx] = t
        bc1 = (1.0 - self.b1 ** t).to(self.params[0].dtype)
        bc2_sqrt = (1.0 - self.b2 ** t).sqrt().to(self.params[0].dtype)
        for p, m, v, g, lr in zip(self.params, self.m, self.v, grads, self.lrs):
            if g is None:
                continue
            shape = (-1,) + (1,) * (g.dim() - 1)
            mi = m.index_select(0, idx).mul_(self.b1).add_(g, alpha=1.0 - self.b1)
            vi = v.index_select(0, idx).mul_(self.b2).addcmul_(g, g, value=1.0 - self.b2)
            m.index_copy_(0, idx, mi)
            v.index_copy_(0, idx, vi)
            # torch's Adam: p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps)
            denom = vi.sqrt().div_(bc2_sqrt.view(shape)).add_(self.eps)
            p.index_add_(0, idx, mi.div_(denom).mul_((-lr / bc1).view(shape)))
