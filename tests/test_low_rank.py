"""The deferred factor gradients of the low-rank updates (mapless.agent.fast_weights.LowRankUpdates)
against plain autograd."""

import pytest
import torch

from mapless.agent.fast_weights import LowRankUpdates, apply_low_rank

B, K, GATES, INPUTS = 3, 4, 8, 5


def _factors(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    left = torch.randn(B, K, GATES, generator=g, dtype=torch.float64, requires_grad=True)
    right = torch.randn(B, K, INPUTS, generator=g, dtype=torch.float64, requires_grad=True)
    return left, right


def _rollout(apply, left, right, inputs, second_order: bool):
    """A few steps that reuse the factors, optionally an inner gradient (create_graph) through them,
    then one outer loss, like the meta-learning inner loop."""
    gates = [apply(x, left, right) for x in inputs]
    loss = sum((g.tanh() ** 2).sum() for g in gates)
    if second_order:
        (inner,) = torch.autograd.grad(sum(g.sin().sum() for g in gates[:2]), inputs[0], create_graph=True)
        loss = loss + (inner**2).sum()
    return loss


@pytest.mark.parametrize("second_order", [False, True])
def test_deferred_factor_gradients_equal_plain_autograd(second_order):
    g = torch.Generator().manual_seed(1)
    left, right = _factors()
    inputs = [torch.randn(B, INPUTS, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(3)]
    wrt = [left, right, *inputs]
    expected = torch.autograd.grad(_rollout(apply_low_rank, left, right, inputs, second_order), wrt)
    updates = LowRankUpdates(left, right)
    got = torch.autograd.grad(_rollout(lambda x, _l, _r: updates(x), left, right, inputs, second_order), wrt)
    for e, a in zip(expected, got, strict=True):
        torch.testing.assert_close(a, e)


def test_factors_built_from_anchored_ones_get_both_gradients():
    """A later stretch concatenates new factors to the anchored ones (an inner step) and selects
    rows (ended episodes dropped): the deferred sums and the ordinary gradients add up."""
    left, right = _factors(2)
    extra_left, extra_right = _factors(3)
    g = torch.Generator().manual_seed(4)
    x1, x2 = (torch.randn(B, INPUTS, generator=g, dtype=torch.float64) for _ in range(2))
    keep = torch.tensor([0, 2])

    def loss_of(apply_first, make_second):
        first = apply_first(x1)
        second_left, second_right, apply_second = make_second()
        second = apply_second(x2[keep], second_left, second_right)
        return (first**2).sum() + (second.cos()).sum()

    def plain_second():
        cat_left = torch.cat([left, extra_left], dim=1)[keep]
        cat_right = torch.cat([right, extra_right], dim=1)[keep]
        return cat_left, cat_right, apply_low_rank

    params = [left, right, extra_left, extra_right]
    expected = torch.autograd.grad(loss_of(lambda x: apply_low_rank(x, left, right), plain_second), params)

    first = LowRankUpdates(left, right)

    def deferred_second():
        second = LowRankUpdates(
            torch.cat([first.left, extra_left], dim=1)[keep],
            torch.cat([first.right, extra_right], dim=1)[keep],
        )
        return second.left, second.right, lambda x, _l, _r: second(x)

    got = torch.autograd.grad(loss_of(first, deferred_second), params)
    for e, a in zip(expected, got, strict=True):
        torch.testing.assert_close(a, e)


def test_constant_factors_take_the_plain_path():
    left, right = (t.detach() for t in _factors(5))
    updates = LowRankUpdates(left, right)
    x = torch.randn(B, INPUTS, dtype=torch.float64)
    assert not updates.deferred
    torch.testing.assert_close(updates(x), apply_low_rank(x, left, right))
