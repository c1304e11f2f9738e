"""mapless.models.dropout.Dropout: the law of nn.Dropout, under vmap too."""

import math

import pytest
import torch
from torch.func import vmap

from mapless.models.dropout import Dropout, keep_mask


@pytest.mark.parametrize("p", [0.25, 0.1, 0.6])
def test_keep_rate_and_scale(p):
    torch.manual_seed(0)
    n = 1_000_000
    keep = keep_mask(torch.Size([n]), p, torch.device("cpu"))
    # Binomial(n, 1 - p): within 5 standard deviations.
    assert abs(keep.double().mean().item() - (1 - p)) < 5 * math.sqrt(p * (1 - p) / n)
    x = torch.full((n,), 2.0)
    out = Dropout(p).train()(x)
    kept = out != 0
    assert torch.allclose(out[kept], torch.tensor(2.0 / (1 - p)), rtol=1e-4)
    assert abs(out.mean().item() - 2.0) < 5 * 2.0 * math.sqrt(p / ((1 - p) * n))


def test_bits_are_independent_between_neighbours():
    """Elements drawn from the same 64-bit word must not be correlated."""
    torch.manual_seed(1)
    keep = keep_mask(torch.Size([400_000, 4]), 0.5, torch.device("cpu")).double()
    corr = torch.corrcoef(keep.T)
    off_diagonal = corr[~torch.eye(4, dtype=torch.bool)]
    assert off_diagonal.abs().max() < 0.01


def test_gradient_is_the_mask_and_eval_is_identity():
    torch.manual_seed(2)
    dropout = Dropout(0.25).train()
    x = torch.randn(64, 32, requires_grad=True)
    out = dropout(x)
    (grad,) = torch.autograd.grad(out.sum(), x)
    assert torch.equal(grad, torch.where(out != 0, 1 / 0.75, 0.0))
    assert dropout.eval()(x) is x
    assert Dropout(0.0).train()(x) is x


def test_reproducible_from_the_seed_and_different_per_episode_under_vmap():
    x = torch.ones(8, 16, 10)

    def run():
        torch.manual_seed(3)
        return vmap(Dropout(0.25).train(), randomness="different")(x)

    first, second = run(), run()
    assert torch.equal(first, second)
    assert not torch.equal(first[0], first[1])  # each episode its own mask
    assert first.dtype == x.dtype


def test_bfloat16_input_keeps_its_dtype():
    x = torch.randn(16, 8, dtype=torch.bfloat16)
    assert Dropout(0.25).train()(x).dtype == torch.bfloat16


def test_invalid_probability_is_rejected():
    with pytest.raises(ValueError, match="dropout probability"):
        Dropout(1.0)
