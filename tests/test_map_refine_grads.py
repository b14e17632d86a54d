"""The map refinement's gradient scatter (`slam.dense.mapping.refine_merged._scatter_grads`) gives exactly the gradient autograd's
indexing gives (backward through tensor[idx]), which it replaces for speed, so torch's Adam takes the same step."""

from __future__ import annotations

import torch

from swarmsplat.slam.dense.mapping.refine_merged import _scatter_grads


def test_scatter_equals_backward_through_indexing():
    g = torch.Generator().manual_seed(0)
    shapes = [(50, 3), (50, 4), (50,)]
    idx = torch.randperm(50, generator=g)[:20]
    upstream = [torch.randn((20,) + s[1:], generator=g) for s in shapes]
    ref = [torch.randn(s, generator=g).requires_grad_(True) for s in shapes]
    torch.autograd.backward([t[idx] for t in ref], upstream)
    ours = [t.detach().clone().requires_grad_(True) for t in ref]
    for t in ours:  # stale gradients from an earlier step must not survive
        t.grad = torch.ones_like(t)
    subs = [t.detach().index_select(0, idx).requires_grad_(True) for t in ours]
    torch.autograd.backward(subs, upstream)
    _scatter_grads(ours, idx, [s.grad for s in subs])
    for a, b in zip(ref, ours):
        assert torch.equal(a.grad, b.grad)
    _scatter_grads(ours[:1], idx, [None])  # no gradient: Adam skips the tensor, as after zero_grad(set_to_none)
    assert ours[0].grad is None
