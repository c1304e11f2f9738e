"""The A3C loss against hand-computed values, and its masking of batched variable-length episodes."""

import math

import pytest
import torch

from mapless.train.a3c_loss import a3c_loss


def test_three_step_episode_matches_hand_values():
    # Uniform policy (zero logits): log π = -log 6 and H = log 6 at every step.
    values = torch.tensor([[0.5], [0.2], [-0.1]])
    rewards = torch.tensor([[-0.01], [-0.01], [5.0]])
    loss = a3c_loss(
        torch.zeros(3, 1, 6), values, torch.zeros(3, 1, dtype=torch.long), rewards, torch.ones(3, 1)
    )
    returns = [0.99 * (0.99 * 5.0 - 0.01) - 0.01, 0.99 * 5.0 - 0.01, 5.0]  # 4.8806, 4.94, 5.0
    value_loss = sum(0.5 * (r - v) ** 2 for r, v in zip(returns, [0.5, 0.2, -0.1], strict=True))
    # τ = 1: GAE = Monte-Carlo advantage R_t - V_t (δ_2 = 5.1, δ_1 = -0.309, δ_0 = -0.312).
    gae = [4.3806, 4.74, 5.1]
    policy = sum(math.log(6) * a - 0.01 * math.log(6) for a in gae)
    assert loss.value.item() == pytest.approx(value_loss, rel=1e-5)
    assert loss.policy.item() == pytest.approx(policy, rel=1e-5)
    assert loss.total.item() == pytest.approx(policy + 0.5 * value_loss, rel=1e-5)
    assert loss.entropy.item() == pytest.approx(3 * math.log(6), rel=1e-6)


def test_gae_tau_and_bootstrap():
    values = torch.tensor([[1.0], [2.0]])
    rewards = torch.tensor([[0.0], [1.0]])
    logits = torch.zeros(2, 1, 6)
    loss = a3c_loss(
        logits,
        values,
        torch.zeros(2, 1, dtype=torch.long),
        rewards,
        torch.ones(2, 1),
        bootstrap=torch.tensor([3.0]),
        tau=0.5,
        beta=0.0,
    )
    d1 = 1.0 + 0.99 * 3.0 - 2.0
    d0 = 0.0 + 0.99 * 2.0 - 1.0
    gae1, gae0 = d1, d1 * 0.99 * 0.5 + d0
    assert loss.policy.item() == pytest.approx(math.log(6) * (gae0 + gae1), rel=1e-6)
    r1 = 1.0 + 0.99 * 3.0
    r0 = 0.99 * r1
    assert loss.value.item() == pytest.approx(0.5 * ((r0 - 1.0) ** 2 + (r1 - 2.0) ** 2), rel=1e-6)


def test_batched_masked_episodes_equal_separate_episodes():
    gen = torch.Generator().manual_seed(0)
    lengths = [5, 2, 4]
    T, B = 5, 3
    logits = torch.randn(T, B, 6, generator=gen)
    values = torch.randn(T, B, 1, generator=gen)
    actions = torch.randint(0, 6, (T, B), generator=gen)
    rewards = torch.randn(T, B, generator=gen)
    mask = torch.stack([torch.arange(T) < n for n in lengths], dim=1).float()
    bootstrap = torch.tensor([0.7, 0.0, -0.3])
    batched = a3c_loss(logits, values, actions, rewards, mask, bootstrap)
    for b, n in enumerate(lengths):
        alone = a3c_loss(
            logits[:n, b : b + 1],
            values[:n, b : b + 1],
            actions[:n, b : b + 1],
            rewards[:n, b : b + 1],
            torch.ones(n, 1),
            bootstrap[b : b + 1],
        )
        for got, want in zip(batched, alone, strict=True):
            assert got[b].item() == pytest.approx(want[0].item(), rel=1e-5, abs=1e-6)
    # Garbage in the padding changes nothing.
    noisy = rewards.clone()
    noisy[mask == 0] = 1e3
    again = a3c_loss(logits, values, actions, noisy, mask, bootstrap)
    assert torch.allclose(again.total, batched.total)


def test_gradients_flow_to_values_and_logits_only_where_real():
    logits = torch.zeros(3, 2, 6, requires_grad=True)
    values = torch.zeros(3, 2, requires_grad=True)
    mask = torch.tensor([[1.0, 1.0], [1.0, 0.0], [1.0, 0.0]])
    loss = a3c_loss(logits, values, torch.zeros(3, 2, dtype=torch.long), torch.ones(3, 2), mask)
    loss.total.sum().backward()
    assert values.grad[1:, 1].abs().sum() == 0 and logits.grad[1:, 1].abs().sum() == 0
    # d total / d V_t = -value_coef * (R_t - V_t) with V = 0: R_2 = 1 for episode 0.
    assert values.grad[2, 0].item() == pytest.approx(-0.5 * 1.0)
    assert values.grad[0, 1].item() == pytest.approx(-0.5 * 1.0)
