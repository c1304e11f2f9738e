"""The one A3C loss of every learned model (SAVN/MJOLNIR ``a3c_loss``, from dgriff777/rl_a3c_pytorch),
for a batch of episodes of different lengths stepped in lockstep.

Per episode, backwards over its valid steps t (``mask[t] = 1``; padding only after an episode's end):

    R      <- γ R + r_t                      R starts at V(s_T) (detached) if the episode was cut, else 0
    value  += ½ (R - V_t)²
    δ_t     = r_t + γ V_{t+1} - V_t          values detached; V_{T} = the bootstrap value
    gae    <- γ τ gae + δ_t
    policy -= log π(a_t | s_t) · gae + β H(π(· | s_t))
    total   = policy + value_coef · value    (so the squared error carries an effective ¼)

Everything is a sum over steps, never a mean (as the reference). The result is per episode; the
reference makes one optimiser step per episode, so a trainer that averages over the batch should say so.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

GAMMA = 0.99
TAU = 1.0
ENTROPY_BETA = 0.01
VALUE_COEF = 0.5


class A3CLoss(NamedTuple):
    """Per-episode ``[B]`` terms: ``total = policy + value_coef * value``; ``entropy`` is Σ_t H_t."""

    total: Tensor
    policy: Tensor
    value: Tensor
    entropy: Tensor


def a3c_loss(
    logits: Tensor,
    values: Tensor,
    actions: Tensor,
    rewards: Tensor,
    mask: Tensor,
    bootstrap: Tensor | None = None,
    gamma: float = GAMMA,
    tau: float = TAU,
    beta: float = ENTROPY_BETA,
    value_coef: float = VALUE_COEF,
) -> A3CLoss:
    """A3C loss of ``B`` episodes over ``T`` lockstep steps.

    :param logits: ``[T, B, A]`` policy logits of each step (computed with whichever parameters acted).
    :param values: ``[T, B]`` or ``[T, B, 1]`` critic outputs.
    :param actions: ``[T, B]`` int actions taken.
    :param rewards: ``[T, B]`` rewards received.
    :param mask: ``[T, B]`` 1 for real steps, 0 for padding after the episode ended (a prefix per column).
    :param bootstrap: ``[B]`` V(s_T) for episodes cut by the rollout horizon, 0 for finished ones
        (detached here); None means every episode finished.
    """
    values = values.reshape(values.shape[0], values.shape[1])
    mask = mask.to(values.dtype)
    rewards = rewards.to(values.dtype)
    log_policy = F.log_softmax(logits, dim=-1)
    entropy = -(log_policy.exp() * log_policy).sum(-1)  # [T, B]
    log_prob = log_policy.gather(-1, actions.long().unsqueeze(-1)).squeeze(-1)

    batch = values.shape[1]
    zero = values.new_zeros(batch)
    R = zero if bootstrap is None else bootstrap.detach().reshape(batch).to(values.dtype)
    next_value = R.clone()
    gae = zero
    policy_loss, value_loss, entropy_sum = zero, zero, zero
    detached = values.detach()
    for t in reversed(range(values.shape[0])):
        m = mask[t]
        # Padded steps leave R, gae and next_value untouched, so each episode's recursion starts at
        # its own last real step.
        R = torch.where(m > 0, gamma * R + rewards[t], R)
        value_loss = value_loss + m * 0.5 * (R - values[t]).pow(2)
        delta = rewards[t] + gamma * next_value - detached[t]
        gae = torch.where(m > 0, gae * gamma * tau + delta, gae)
        next_value = torch.where(m > 0, detached[t], next_value)
        policy_loss = policy_loss - m * (log_prob[t] * gae + beta * entropy[t])
        entropy_sum = entropy_sum + m * entropy[t]
    return A3CLoss(policy_loss + value_coef * value_loss, policy_loss, value_loss, entropy_sum)
