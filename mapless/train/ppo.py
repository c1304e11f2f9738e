"""The PPO trainer (``algo: ppo``): recurrent PPO over the batched environment, CleanRL's recipe,
with its two pure pieces (Schulman et al. 2017): generalised advantage estimation over a segment
(:func:`gae`) and the clipped surrogate with value and entropy terms (:func:`ppo_loss`).

Per update::

    segment = collector.collect(ppo.steps)         # N slots; finished slots take new episodes
    advantages, returns = gae(segment)             # bootstrapped at segment ends and truncations
    repeat ppo.epochs times:
        for each of ppo.minibatches sets of whole slot sequences:
            logits, values = replay(set)           # from the segment's first step, same recurrent state
            loss = clipped surrogate + value_coef * value loss - entropy_coef * entropy
            backward, all-reduce over ranks, clip, Adam step

Adaptive models (savn, gve, spatt, cvmeta) play whole episodes (the others too with
``ppo.whole_episodes``, replayed from their first step) and replay each one through the
meta-learning inner loop (:class:`~mapless.agent.meta.InnerLoop`), recomputed in every minibatch from
the current parameters. SAVN's schedule, the default: after every k = ``model.interaction_steps``
steps (at most ``model.max_inner_updates`` times) the fast weights take one SGD step on the learned
interaction loss of the last k steps, and the PPO loss reads every step of the episode, each with the
weights that acted. The paper's text instead adapts once after the first k steps and computes the
navigation loss on the rest: ``model.max_inner_updates: 1`` with ``ppo.meta.navigation_loss:
after_interaction``. The meta-gradient (second order, or first order with ``meta.first_order``) flows
through the adaptation. The probability ratio is that of the adapted policy against the adapted
policy that acted.

With ``ppo.imitation_coef`` > 0 the loss also holds the cross-entropy to the simulator's
shortest-path expert on the agent's own steps (an imitation warm start, annealed over
``ppo.imitation_frames``; off in the paper's protocol). While it is on, the learned loss φ takes no
step (``ppo.meta.learned_loss_from_imitation``): φ is meta-trained to stand in for the navigation loss,
never for the expert's cross-entropy, which no test-time agent has. ``ppo.meta.train_learned_loss:
false`` freezes φ at its initialisation in every update (an ablation).

PPO trains with dropout off (the model in ``eval()`` mode), because the ratio compares the policy
that acted with the same function under new parameters. The seeds, model, environment, random
streams, run folder, checkpoints, budget, logs and graceful stop are those of the base it shares
with the batched A3C trainer, its sibling (:class:`~mapless.train.synchronous.SynchronousTrainer`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapless.agent.meta import InnerLoop, InnerLoopState
from mapless.models.memo import InViewMemo
from mapless.train import distributed as dist
from mapless.train.monitor import RunMonitor
from mapless.train.segments import Segment, SegmentCollector
from mapless.train.synchronous import SynchronousTrainer


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


_EPISODE_ROWS = ("success", "spl", "length", "reward")
_LOSS_KEYS = ("total", "policy", "value", "entropy", "approx_kl", "clip_fraction")


class PPOTrainer(SynchronousTrainer):
    label = "ppo"

    _imitation_loss = 0.0  # this update's sum of the expert cross-entropy over its minibatches

    def _environment_slots(self) -> int:
        return self.config.ppo.envs

    def _build_algorithm(self) -> None:
        cfg = self.config
        self.model.eval()  # dropout off: see the module docstring
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.ppo.lr, eps=cfg.ppo.adam_eps)
        adaptive = self.model.adaptive
        self.collector = SegmentCollector(
            self.model,
            self.env,
            self.sampler,
            self.obs_keys,
            self.device,
            whole_episodes=adaptive or cfg.ppo.whole_episodes,
            adapting=adaptive,
            expert=cfg.ppo.imitation_coef > 0,
            bootstrap_time_limit=cfg.ppo.bootstrap_time_limit,
        )
        self.inner = InnerLoop(self.model, first_order=cfg.meta.first_order) if adaptive else None
        named = dict(self.model.named_parameters())
        self._learned_loss_params = (
            [named[n] for n in self.model.learned_loss_parameter_names()] if adaptive else []
        )

    @property
    def rollout_steps(self) -> int:
        """Steps per collection: the step limit for whole episodes (they run to their end), else
        the segment length."""
        return self.config.env.max_steps if self.collector.whole_episodes else self.config.ppo.steps

    def _rng_state(self) -> dict:
        return {**super()._rng_state(), "collector": self.collector.state_dict()}

    def _restore(self, state: dict) -> None:
        super()._restore(state)
        rngs = state.get("rng", [])
        if self.ctx.rank < len(rngs) and "collector" in rngs[self.ctx.rank]:
            self.collector.load_state_dict(rngs[self.ctx.rank]["collector"])

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> dict[str, Any]:
        ppo = self.config.ppo
        segment = self.collector.collect(self.rollout_steps, self.rng)
        advantages, returns = gae(
            segment.rewards,
            segment.values,
            segment.next_value,
            segment.terminated,
            segment.truncated,
            segment.bootstrap,
            ppo.gamma,
            ppo.lam,
        )
        lr = self._learning_rate()
        imitation = self._imitation_weight()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        sums = dict.fromkeys(_LOSS_KEYS, 0.0)
        self._imitation_loss = 0.0
        grad_norms = []
        slots = segment.mask.shape[1]
        for _ in range(ppo.epochs):
            order = torch.from_numpy(self.rng.permutation(slots)).to(self.device)
            for minibatch in order.chunk(ppo.minibatches):
                loss = self.minibatch_step(segment, minibatch, advantages, returns, imitation)
                grad_norms.append(self._step())
                for key in _LOSS_KEYS:
                    sums[key] += float(getattr(loss, key))
        passes = ppo.epochs * ppo.minibatches
        mask = segment.mask > 0
        residual = (returns - segment.values)[mask]
        variance = returns[mask].var() if mask.sum() > 1 else returns.new_ones(())
        explained = float(1.0 - residual.var() / variance) if variance > 0 else 0.0
        return {
            "segment": segment,
            "losses": {key: value / passes for key, value in sums.items()},
            "grad_norm": float(np.mean(grad_norms)),
            "scalars": {
                "ppo/explained_variance": explained,
                "ppo/lr": lr,
                "ppo/imitation_coef": imitation,
                "ppo/imitation_loss": self._imitation_loss / passes,
            },
        }

    def _learning_rate(self) -> float:
        cfg = self.config
        if not cfg.ppo.lr_decay:
            return cfg.ppo.lr
        if cfg.frames > 0:
            done = self.counters["frames"] / cfg.frames
        else:
            done = self.counters["episodes"] / cfg.episodes
        return cfg.ppo.lr * max(1.0 - done, 0.0)

    def _imitation_weight(self) -> float:
        ppo = self.config.ppo
        if ppo.imitation_frames == 0:
            return ppo.imitation_coef
        return ppo.imitation_coef * max(1.0 - self.counters["frames"] / ppo.imitation_frames, 0.0)

    def minibatch_step(
        self, segment: Segment, columns: Tensor, advantages: Tensor, returns: Tensor, imitation: float = 0.0
    ) -> PPOLoss:
        """Replay the slots ``columns`` with the current parameters and backpropagate PPO's loss
        into ``.grad`` (the optimizer step is :meth:`update`'s). ``imitation``: the weight of the
        expert cross-entropy in the loss (:meth:`update` passes ``ppo.imitation_coef``, annealed;
        0, no expert term)."""
        ppo = self.config.ppo
        self.optimizer.zero_grad(set_to_none=True)
        mask = segment.mask[:, columns]
        if self.inner is not None and self.config.ppo.meta.navigation_loss == "after_interaction":
            # The paper's L_nav reads D_nav, the steps after the first k (the interaction phase).
            mask = mask.clone()
            mask[: self.model.config.interaction_steps] = 0
        advantage = advantages[:, columns]
        if ppo.normalize_advantages and bool((mask > 0).any()):  # none: every step out of the loss
            valid = advantage[mask > 0]
            advantage = (advantage - valid.mean()) / (valid.std(unbiased=False) + 1e-8)
        # Whole episodes: a slot idles after its episode ends; its padded steps go unencoded.
        acted = segment.mask[:, columns] > 0 if self.collector.whole_episodes else None
        with self.model.memoizing_in_view(InViewMemo(max_rows=None)):
            logits, values, state = self._replay(
                {k: v[:, columns] for k, v in segment.obs.items()},
                segment.prev_policy[:, columns],
                segment.starts[:, columns],
                tuple(t.index_select(0, columns) for t in segment.hidden),
                acted,
            )
        steps = logits.shape[0]
        loss = ppo_loss(
            logits,
            values,
            segment.actions[:steps, columns],
            segment.log_prob[:steps, columns],
            segment.values[:steps, columns],
            advantage[:steps],
            returns[:steps, columns],
            mask[:steps],
            clip=ppo.clip,
            value_clip=ppo.value_clip,
            value_coef=ppo.value_coef,
            entropy_coef=ppo.entropy_coef,
        )
        total = loss.total
        if imitation > 0:
            expert = segment.expert[:steps, columns]
            known = (expert >= 0) & (mask[:steps] > 0)
            if bool(known.any()):
                cross_entropy = F.cross_entropy(logits[known], expert[known])
                total = total + imitation * cross_entropy
                self._imitation_loss += float(cross_entropy.detach())
        if state is None:
            total.backward()
        else:
            self.inner.backward(state, total)
            meta = self.config.ppo.meta
            if not meta.train_learned_loss or (imitation > 0 and not meta.learned_loss_from_imitation):
                # φ must learn to stand in for the navigation loss, not for the expert's
                # cross-entropy, which does not exist at test time: no φ step in this update.
                # (A frozen φ, the ablation, takes none in any update.)
                for param in self._learned_loss_params:
                    param.grad = None
        return PPOLoss(*(t.detach() for t in loss))

    def _replay(
        self,
        obs: dict[str, Tensor],
        prev_policy: Tensor,
        starts: Tensor,
        hidden: tuple[Tensor, Tensor],
        acted: Tensor | None,
    ) -> tuple[Tensor, Tensor, InnerLoopState | None]:
        """``(logits, values, inner-loop state)`` of a minibatch's segment under the current
        parameters: an adaptive model's whole episodes through the inner loop
        (:meth:`InnerLoop.replay`, from their first step: ``starts`` and ``hidden`` are implied),
        any other model's through :meth:`~mapless.models.base.RecurrentNavModel.replay` (no state:
        a loss of its outputs backpropagates as usual)."""
        if self.inner is not None:
            return self.inner.replay(obs, prev_policy, acted)
        logits, values = self.model.replay(obs, prev_policy, starts, hidden, acted)
        return logits, values, None

    def _step(self) -> float:
        dist.all_reduce_gradients(self.params, self.ctx)
        params = [p for p in self.params if p.grad is not None]
        norm = torch.nn.utils.get_total_norm([p.grad for p in params])
        self._check_finite(float(norm))
        if self.config.ppo.max_grad_norm > 0:
            torch.nn.utils.clip_grads_with_norm_(params, self.config.ppo.max_grad_norm, norm)
        self.optimizer.step()
        return float(norm)

    # -- statistics ------------------------------------------------------------------------------
    def _account(self, result: dict[str, Any], monitor: RunMonitor, stop_requested: bool) -> bool:
        segment: Segment = result["segment"]
        finished = dist.gather_objects(segment.finished, self.ctx)
        rows = {key: np.concatenate([f[key] for f in finished]) for key in _EPISODE_ROWS}
        totals = dist.all_reduce_sum(
            torch.tensor(
                [float(segment.frames), float(stop_requested), self._out_of_time_here()], dtype=torch.float64
            ),
            self.ctx,
        )
        episodes = len(rows["success"])
        losses = result["losses"]
        count = max(episodes, 1)
        monitor.add_episodes(*(rows[key] for key in _EPISODE_ROWS))
        monitor.add_losses(
            losses["total"], losses["policy"], losses["value"], losses["entropy"], result["grad_norm"], count
        )
        monitor.add_scalars(
            {
                "ppo/approx_kl": losses["approx_kl"],
                "ppo/clip_fraction": losses["clip_fraction"],
                **result["scalars"],
            },
            count,
        )
        return self._advance(monitor, episodes, int(totals[0]), bool(totals[1] > 0), bool(totals[2] > 0))
