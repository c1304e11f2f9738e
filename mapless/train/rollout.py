"""Acting and the per-episode loss, shared by both trainers.

Two rollout loops produce the same :class:`Trajectory` layout (``[T, B, ...]`` per step):

* :func:`run_episode` plays one episode in the gymnasium :class:`~mapless.sim.env.NavEnv` at batch size
  1, as a reference worker does (the ``async`` trainer);
* :func:`run_batch` plays ``B`` episodes in lockstep in :class:`~mapless.sim.vector.BatchedNavEnv` with one
  batched forward per step (the ``batched`` trainer).

Actions are drawn by inverse-CDF sampling from uniform noise that the caller draws per episode
(``noise [B, T]``), so the action sequence of an episode depends only on its own noise row and its
policy, not on how many episodes are stepped together. That is what makes the two loops comparable
episode by episode (tests/test_train_equivalence.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from mapless.agent.acting import sample_actions, to_tensors
from mapless.agent.buffers import BufferPool
from mapless.agent.meta import InnerLoop, InnerLoopState
from mapless.agent.precision import PRECISIONS, encoder_autocast, like
from mapless.agent.rollout_lstm import RolloutLstm, accumulate_grad
from mapless.models.base import NUM_ACTIONS, ModelOutput, NavModel, RecurrentNavModel, lstm_state_from_gates
from mapless.models.memo import InViewMemo
from mapless.sim.env import NavEnv
from mapless.sim.episode import Episode
from mapless.sim.vector import BatchedNavEnv
from mapless.train.a3c_loss import A3CLoss, a3c_loss
from mapless.train.config import LossConfig


@dataclass
class Trajectory:
    """Lockstep record of ``B`` episodes over ``T`` steps (padding after an episode's end has mask 0)."""

    logits: Tensor  # [T, B, A] with grad
    values: Tensor  # [T, B] with grad
    actions: Tensor  # [T, B]
    rewards: Tensor  # [T, B]
    mask: Tensor  # [T, B]
    success: np.ndarray  # [B] bool
    length: np.ndarray  # [B] steps taken, the final Done included (SAVN's len(path))
    optimal_length: np.ndarray  # [B] shortest path in actions incl. Done, -1 if unknown

    @property
    def frames(self) -> int:
        return int(self.length.sum())

    def spl(self) -> np.ndarray:
        opt = self.optimal_length.astype(np.float64)
        ok = self.success & (opt > 0)
        return np.where(ok, opt / np.maximum(self.length, np.maximum(opt, 1)), 0.0)

    def total_reward(self) -> np.ndarray:
        return (self.rewards * self.mask).sum(0).cpu().numpy()


class Actor:
    """Forward pass of a plain model or, for adaptive models in training, of the batched inner loop.

    Both run the model's LSTM through a :class:`~mapless.agent.rollout_lstm.RolloutLstm` (one weight
    gradient per rollout instead of one per step). :func:`run_batch` steps only the episodes still
    running, so no forward pass is computed for finished ones; :meth:`compact` drops them from the
    inner loop's per-episode fast weights too.
    """

    def __init__(self, model: NavModel, inner: InnerLoop | None, dtype: torch.dtype | None = None):
        """``dtype``: compute dtype of a plain model's encoders and LSTM products
        (:mod:`mapless.agent.precision`; the inner loop has its own)."""
        self.model = model
        self.inner = inner
        self.dtype = dtype
        self.state: InnerLoopState | None = None
        self.lstm: RolloutLstm | None = None
        self.memo: InViewMemo | None = None
        self.buffers = BufferPool()  # a plain model's LSTM operand and weight gradients, per rollout

    def start(self, batch_size: int) -> None:
        # The parameters stay fixed until the update: the object GCNs' results can be reused
        # across the rollout's steps (mapless.models.memo).
        self.memo = InViewMemo(max_rows=None)
        self.state = self.inner.start(batch_size) if self.inner is not None else None
        if self.inner is None and isinstance(self.model, RecurrentNavModel) and torch.is_grad_enabled():
            self.lstm = RolloutLstm(self.model.lstm, dtype=self.dtype, buffers=self.buffers)
        else:
            self.lstm = None

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        with self.model.memoizing_in_view(self.memo):
            return self._forward(obs, hidden, prev_policy)

    def _forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        if self.inner is not None:
            return self.inner.forward(self.state, obs, hidden, prev_policy)
        if self.lstm is None:
            return self.model(obs, hidden, prev_policy)
        model, cell = self.model, self.model.lstm
        with encoder_autocast(self.dtype, hidden[0].device):
            x, critic_input = model.encode(model.describe(obs), hidden, prev_policy)
        x, critic_input = like(x, hidden[0]), like(critic_input, hidden[0])
        _, product = self.lstm.gates(x, hidden[0])
        h, c = lstm_state_from_gates(product + cell.bias_ih + cell.bias_hh, hidden[1])
        return ModelOutput(model.actor_linear(h), model.value(h, critic_input), (h, c))

    def observe(self, output: ModelOutput, alive: Tensor) -> None:
        if self.inner is not None:
            self.inner.observe(self.state, output, alive)

    def compact(self, keep: Tensor) -> None:
        """Keep only the rows ``keep`` (indices into the current batch) of the inner-loop state.

        Ended episodes never adapt again and their later outputs are masked out of the loss, so
        dropping them changes nothing for the others (:meth:`InnerLoop.compact`)."""
        if self.state is not None:
            self.inner.compact(self.state, keep)

    def backward(self, loss: Tensor) -> None:
        """Accumulate the gradient (adaptive models: the meta-gradient) of ``loss`` into ``.grad``."""
        if self.inner is not None:
            self.inner.backward(self.state, loss)
        else:
            params = [p for p in self.model.parameters() if p.requires_grad]
            grads = self.gradients(loss, params)
            accumulate_grad(params, grads, adopt=self.lstm.weight_gradients if self.lstm else ())

    def gradients(
        self, loss: Tensor, params: list[Tensor], retain_graph: bool = False
    ) -> tuple[Tensor | None, ...]:
        """``torch.autograd.grad(loss, params, allow_unused=True)`` of this rollout, the deferred LSTM
        matrix gradients included. For adaptive models that is the second-order meta-gradient, even
        when the actor was made with ``first_order=True`` (only :meth:`backward` applies that option);
        tests use it to take per-episode gradients from a batched rollout."""
        lstm = self.state.lstm if self.state is not None else self.lstm
        if lstm is None:
            return torch.autograd.grad(loss, params, retain_graph=retain_graph, allow_unused=True)
        return lstm.grad(loss, params, retain_graph)


def make_actor(model: NavModel, first_order: bool = False, precision: str = "fp32") -> Actor:
    """The training actor of ``model`` at ``precision`` (``fp32`` or ``bf16``, :mod:`mapless.agent.precision`)."""
    dtype = PRECISIONS[precision]
    inner = InnerLoop(model, first_order=first_order, dtype=dtype) if model.adaptive else None
    return Actor(model, inner, dtype)


def _stack(
    logits: list[Tensor],
    values: list[Tensor],
    actions: list[Tensor],
    rewards: list[np.ndarray],
    mask: list[np.ndarray],
    device: torch.device,
) -> tuple[Tensor, ...]:
    return (
        torch.stack(logits),
        torch.stack(values).squeeze(-1),
        torch.stack(actions),
        torch.as_tensor(np.stack(rewards), device=device),
        torch.as_tensor(np.stack(mask), device=device),
    )


def run_batch(
    actor: Actor,
    env: BatchedNavEnv,
    episodes: list[Episode],
    noise: np.ndarray,
    obs_keys: tuple[str, ...],
    device: torch.device,
) -> Trajectory:
    """Play ``episodes`` to their end in lockstep (slot ``b`` uses ``noise[b, t]`` at step ``t``).

    Only the episodes still running are stepped through the model (``slots``: their indices in the
    batch); the per-step outputs are scattered back to full ``[B]`` rows, zero where an episode has
    already ended (those entries have mask 0)."""
    batch = len(episodes)
    env.reset(np.arange(batch), episodes)
    actor.start(batch)
    hidden = actor.model.initial_state(batch, device)
    prev_policy = torch.zeros(batch, NUM_ACTIONS, device=device)
    noise_t = torch.as_tensor(noise, dtype=torch.float32, device=device)
    slots = np.arange(batch)
    slots_t = torch.as_tensor(slots, device=device)
    logits, values, actions, rewards, mask = [], [], [], [], []
    success = np.zeros(batch, dtype=bool)
    for t in range(noise.shape[1]):
        obs = {key: value[slots] for key, value in env.observe(obs_keys).items()}
        out = actor.forward(to_tensors(obs, device), hidden, prev_policy)
        action = sample_actions(out.logits, noise_t[slots_t, t])
        full_action = torch.zeros(batch, dtype=torch.long, device=device).index_copy(0, slots_t, action)
        step = env.step(full_action.cpu().numpy())
        success |= step.success
        logits.append(out.logits.new_zeros(batch, NUM_ACTIONS).index_copy(0, slots_t, out.logits))
        values.append(out.value.new_zeros(batch, 1).index_copy(0, slots_t, out.value))
        actions.append(full_action)
        rewards.append(step.reward)
        mask.append(step.active.astype(np.float32))
        # SAVN feeds the previous step's policy (not detached) and carries (h, c) through the episode.
        hidden, prev_policy = out.hidden, torch.softmax(out.logits, dim=-1)
        alive = ~env.done[slots]
        actor.observe(out, torch.as_tensor(alive, device=device))
        if not alive.any():
            break
        if not alive.all():
            keep = torch.as_tensor(np.flatnonzero(alive), device=device)
            slots, slots_t = slots[alive], slots_t.index_select(0, keep)
            hidden = (hidden[0].index_select(0, keep), hidden[1].index_select(0, keep))
            prev_policy = prev_policy.index_select(0, keep)
            actor.compact(keep)
    stacked = _stack(logits, values, actions, rewards, mask, device)
    return Trajectory(
        *stacked, success=success, length=env.steps.copy(), optimal_length=env.optimal_length.copy()
    )


def run_episode(
    actor: Actor,
    env: NavEnv,
    episode: Episode,
    noise: np.ndarray,
    obs_keys: tuple[str, ...],
    device: torch.device,
) -> Trajectory:
    """Play one episode at batch size 1, the way a reference worker does (``noise [T]``)."""
    obs, info = env.reset(options={"episode": episode})
    actor.start(1)
    hidden = actor.model.initial_state(1, device)
    prev_policy = torch.zeros(1, NUM_ACTIONS, device=device)
    logits, values, actions, rewards, mask = [], [], [], [], []
    success, steps = False, 0
    for t in range(len(noise)):
        out = actor.forward(
            to_tensors({k: obs[k] for k in obs_keys}, device, batch=False), hidden, prev_policy
        )
        action = sample_actions(out.logits, torch.full((1,), float(noise[t]), device=device))
        obs, reward, terminated, truncated, info = env.step(int(action))
        steps += 1
        success = bool(info["success"])
        logits.append(out.logits)
        values.append(out.value)
        actions.append(action)
        rewards.append(np.array([reward], dtype=np.float32))
        mask.append(np.ones(1, dtype=np.float32))
        hidden, prev_policy = out.hidden, torch.softmax(out.logits, dim=-1)
        done = terminated or truncated
        actor.observe(out, torch.tensor([not done], device=device))
        if done:
            break
    stacked = _stack(logits, values, actions, rewards, mask, device)
    return Trajectory(
        *stacked,
        success=np.array([success]),
        length=np.array([steps]),
        optimal_length=np.array([info["optimal_length"]]),
    )


def episode_losses(trajectory: Trajectory, config: LossConfig) -> A3CLoss:
    """Per-episode A3C loss terms ``[B]``. Every training episode ends (Done or the 30-step limit)
    before the update, so nothing is bootstrapped (the references' R = 0)."""
    return a3c_loss(
        trajectory.logits,
        trajectory.values,
        trajectory.actions,
        trajectory.rewards,
        trajectory.mask,
        None,
        gamma=config.gamma,
        tau=config.tau,
        beta=config.beta,
        value_coef=config.value_coef,
    )


def accumulate_gradients(actor: Actor, trajectory: Trajectory, config: LossConfig) -> A3CLoss:
    """Backpropagate the *mean* per-episode loss of the batch into ``.grad`` (the mean of the
    per-episode gradients, so one batched update moves as far as one reference update would with the
    average episode; at B = 1 it is exactly the reference's gradient)."""
    losses = episode_losses(trajectory, config)
    actor.backward(losses.total.mean())
    return losses
