"""slam.dense.mapping.selective_adam against torch.optim.Adam: rows in every step follow torch's Adam exactly; rows outside a
step do not move; a row's bias correction counts only its own steps."""

from __future__ import annotations

import pytest
import torch

from swarmsplat.slam.dense.mapping.selective_adam import SelectiveAdam


def _grad(step: int, shape) -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(100 + step), dtype=torch.float64)


def test_rows_in_every_step_follow_torch_adam():
    a0 = torch.randn(6, 3, dtype=torch.float64)
    b0 = torch.randn(6, dtype=torch.float64)
    ours = [a0.clone(), b0.clone()]
    opt = SelectiveAdam(ours, [1e-2, 3e-3], eps=1e-12)
    ref = [a0.clone().requires_grad_(True), b0.clone().requires_grad_(True)]
    ref_opt = torch.optim.Adam([{"params": [ref[0]], "lr": 1e-2}, {"params": [ref[1]], "lr": 3e-3}], eps=1e-12)
    idx = torch.tensor([0, 2, 5])
    for s in range(25):
        ga, gb = _grad(s, (3, 3)), _grad(1000 + s, (3,))
        opt.step(idx, [ga, gb])
        ref_opt.zero_grad()
        full_a, full_b = torch.zeros(6, 3, dtype=torch.float64), torch.zeros(6, dtype=torch.float64)
        full_a[idx], full_b[idx] = ga, gb
        ref[0].grad, ref[1].grad = full_a, full_b
        ref_opt.step()
    assert torch.allclose(ours[0][idx], ref[0].detach()[idx], rtol=1e-10, atol=1e-12)
    assert torch.allclose(ours[1][idx], ref[1].detach()[idx], rtol=1e-10, atol=1e-12)
    # the rows no step touched are exactly where they started; torch's Adam never moved them either (zero moments)
    rest = torch.tensor([1, 3, 4])
    assert torch.equal(ours[0][rest], a0[rest]) and torch.equal(ours[1][rest], b0[rest])


def test_a_row_outside_a_step_keeps_its_value_and_its_own_bias_correction():
    p = torch.zeros(2, 1, dtype=torch.float64)
    opt = SelectiveAdam([p], [0.1])
    opt.step(torch.tensor([0]), [torch.ones(1, 1, dtype=torch.float64)])
    assert p[1, 0].item() == 0.0 and p[0, 0].item() == pytest.approx(-0.1)  # Adam's first step is -lr sign(g)
    opt.step(torch.tensor([1]), [torch.ones(1, 1, dtype=torch.float64)])
    # row 1's first step is a first step too (its own bias correction), not a second step of row 0's
    assert p[1, 0].item() == pytest.approx(-0.1) and p[0, 0].item() == pytest.approx(-0.1)


def test_bad_arguments():
    with pytest.raises(ValueError, match="one learning rate"):
        SelectiveAdam([torch.zeros(3)], [0.1, 0.2])
    with pytest.raises(ValueError, match="same number of rows"):
        SelectiveAdam([torch.zeros(3), torch.zeros(4)], [0.1, 0.2])
