"""The two pure pieces of PPO (Schulman et al. 2017), as CleanRL writes them: generalised advantage
estimation over a segment, and the clipped surrogate with value and entropy terms."""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor


def gae(
    rewards: Tensor,
    values: Tensor,
    next_value: Tensor,
    terminated: Tensor,
    truncated: Tensor,
    bootstrap: Tensor,
    gamma: float,
    lam: float,
) -> tuple[Tensor, Tensor]:
    """Advantages and returns ``[T, B]`` of a segment of ``T`` steps in ``B`` environment slots.

    Step ``t`` of slot ``b`` took the action in state ``s_t`` (value ``values[t]``) and received
    ``rewards[t]``. If its episode ended at that step, ``terminated`` (Done, or a real end: no future)
    or ``truncated`` (the time limit: the future exists and is worth ``bootstrap[t]`` = V(s_{t+1})) is
    set, and the next row of the slot belongs to a new episode. ``next_value [B]`` is V of the state
    after the segment's last step (its slot's episode goes on in the next segment).

        δ_t = r_t + γ V_next(t) - V_t,   V_next(t) = 0 if terminated, bootstrap[t] if truncated,
                                          else values[t + 1] (next_value at the last step)
        A_t = δ_t + γ λ (1 - ended_t) A_{t+1}
        R_t = A_t + V_t
    """
    terminated, truncated = terminated.to(values.dtype), truncated.to(values.dtype)
    ended = torch.clamp(terminated + truncated, max=1.0)
    following = torch.cat([values[1:], next_value.unsqueeze(0)])
    next_values = (1.0 - ended) * following + truncated * bootstrap
    deltas = rewards + gamma * next_values - values
    advantages = torch.zeros_like(values)
    running = torch.zeros_like(next_value)
    for t in reversed(range(values.shape[0])):
        running = deltas[t] + gamma * lam * (1.0 - ended[t]) * running
        advantages[t] = running
    return advantages, advantages + values


class PPOLoss(NamedTuple):
    """Scalars of one minibatch: ``total = policy + value_coef * value - entropy_coef * entropy``,
    and the diagnostics CleanRL logs (approximate KL ``mean((r - 1) - log r)``, clip fraction)."""

    total: Tensor
    policy: Tensor
    value: Tensor
    entropy: Tensor
    approx_kl: Tensor
    clip_fraction: Tensor


def ppo_loss(
    logits: Tensor,
    values: Tensor,
    actions: Tensor,
    old_log_prob: Tensor,
    old_values: Tensor,
    advantages: Tensor,
    returns: Tensor,
    mask: Tensor,
    clip: float,
    value_clip: float,
    value_coef: float,
    entropy_coef: float,
) -> PPOLoss:
    """Clipped-surrogate PPO loss over the steps where ``mask`` is 1 (means over those steps).

    :param logits: ``[..., A]`` current policy logits; ``values``: ``[...]`` current values.
    :param old_log_prob, old_values: what the acting policy computed (constants).
    :param advantages: normalise them before if wanted (the trainer does, per minibatch).
    :param value_clip: clip the value change to ±value_clip around ``old_values`` (0 = off).
    """
    mask = mask.to(values.dtype)
    count = mask.sum().clamp(min=1.0)
    log_policy = F.log_softmax(logits, dim=-1)
    log_prob = log_policy.gather(-1, actions.long().unsqueeze(-1)).squeeze(-1)
    entropy = -(log_policy.exp() * log_policy).sum(-1)
    log_ratio = log_prob - old_log_prob
    ratio = log_ratio.exp()
    surrogate = torch.max(-advantages * ratio, -advantages * ratio.clamp(1.0 - clip, 1.0 + clip))
    if value_clip > 0:
        clipped = old_values + (values - old_values).clamp(-value_clip, value_clip)
        value_error = torch.max((values - returns) ** 2, (clipped - returns) ** 2)
    else:
        value_error = (values - returns) ** 2

    def mean(x: Tensor) -> Tensor:
        return (x * mask).sum() / count

    policy, value, ent = mean(surrogate), 0.5 * mean(value_error), mean(entropy)
    with torch.no_grad():
        approx_kl = mean((ratio - 1.0) - log_ratio)
        clip_fraction = mean(((ratio - 1.0).abs() > clip).to(values.dtype))
    return PPOLoss(
        policy + value_coef * value - entropy_coef * ent, policy, value, ent, approx_kl, clip_fraction
    )
