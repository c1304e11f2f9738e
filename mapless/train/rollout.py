"""Acting and the per-episode loss of the references' A3C recipe, shared by both of its trainers.

:func:`run_batch` plays ``B`` episodes in lockstep to their end through the one episode loop
(:class:`~mapless.agent.episode_loop.EpisodeLoop`), with one batched forward per step of the episodes
still running, and returns a :class:`Trajectory` (``[T, B, ...]`` per step). The ``batched`` trainer
calls it with its batch; the ``async`` trainer's workers call it at B = 1, as a reference worker plays.

Actions are drawn by inverse-CDF sampling from uniform noise that the caller draws per episode
(``noise [B, T]``), so the action sequence of an episode depends only on its own noise row and its
policy, not on how many episodes are stepped together. That is what makes the batch comparable
episode by episode with B = 1 (tests/test_train_equivalence.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from mapless.agent.acting import PolicyMemory, policy_probabilities, sample_actions, to_tensors
from mapless.agent.buffers import BufferPool
from mapless.agent.episode_loop import EpisodeLoop
from mapless.agent.meta import InnerLoop, InnerLoopState
from mapless.agent.precision import PRECISIONS
from mapless.agent.rollout_lstm import RolloutLstm, accumulate_grad
from mapless.evaluate.metrics import spl
from mapless.models.base import NUM_ACTIONS, ModelOutput, NavModel, RecurrentNavModel
from mapless.models.memo import InViewMemo
from mapless.sim.episode import Episode
from mapless.sim.vector import BatchedNavEnv, BatchStep
from mapless.train.a3c_loss import A3CLoss, a3c_loss
from mapless.train.config import A3CConfig


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
        return np.array(
            [spl(*episode) for episode in zip(self.success, self.length, self.optimal_length, strict=True)]
        )

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
            self.lstm = RolloutLstm(self.model.recurrent_cell, dtype=self.dtype, buffers=self.buffers)
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
        return self.model.rollout_step(obs, hidden, prev_policy, self.lstm)

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


class _LockstepRecorder:
    """The :class:`~mapless.agent.episode_loop.LoopAgent` of :func:`run_batch`: acts through ``actor``
    for the episodes still running and records every step as full ``[B]`` rows."""

    def __init__(self, actor: Actor, noise: np.ndarray, obs_keys: tuple[str, ...], device: torch.device):
        self.actor, self.device = actor, device
        self.observation_keys = obs_keys
        self.noise = noise
        self.batch = noise.shape[0]
        self.memory = PolicyMemory(actor.model, self.batch, device)
        self.rows = torch.arange(self.batch, device=device)  # batch rows of the actor's current rows
        self.output: ModelOutput | None = None
        self.logits: list[Tensor] = []
        self.values: list[Tensor] = []
        self.actions: list[Tensor] = []
        self.rewards: list[np.ndarray] = []
        self.mask: list[np.ndarray] = []
        self.success = np.zeros(self.batch, dtype=bool)

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        self.actor.start(self.batch)

    def act(self, obs: dict[str, np.ndarray], slots: np.ndarray, env: BatchedNavEnv) -> np.ndarray:
        if len(slots) < len(self.rows):  # episodes ended: drop their rows from the actor's state
            keep = torch.as_tensor(
                np.flatnonzero(np.isin(self.rows.cpu().numpy(), slots)), device=self.device
            )
            self.rows = self.rows.index_select(0, keep)
            self.memory.keep(keep)
            self.actor.compact(keep)
        memory = self.memory
        self.output = self.actor.forward(to_tensors(obs, self.device), memory.hidden, memory.prev_policy)
        t = len(self.logits)
        return sample_actions(
            policy_probabilities(self.output.logits), self.noise[self.rows.cpu().numpy(), t]
        )

    def after_step(self, slots: np.ndarray, actions: np.ndarray, step: BatchStep, env: BatchedNavEnv) -> None:
        out, rows = self.output, self.rows
        self.success |= step.success
        self.logits.append(out.logits.new_zeros(self.batch, NUM_ACTIONS).index_copy(0, rows, out.logits))
        self.values.append(out.value.new_zeros(self.batch, 1).index_copy(0, rows, out.value))
        self.actions.append(torch.as_tensor(actions, device=self.device))
        self.rewards.append(step.reward)
        self.mask.append(step.active.astype(np.float32))
        # SAVN feeds the previous step's policy (not detached) and carries (h, c) through the episode.
        self.memory.advance(out)
        self.actor.observe(out, torch.as_tensor(~env.done[slots], device=self.device))

    def trajectory(self, env: BatchedNavEnv) -> Trajectory:
        device = self.device
        return Trajectory(
            torch.stack(self.logits),
            torch.stack(self.values).squeeze(-1),
            torch.stack(self.actions),
            torch.as_tensor(np.stack(self.rewards), device=device),
            torch.as_tensor(np.stack(self.mask), device=device),
            success=self.success,
            length=env.steps.copy(),
            optimal_length=env.optimal_length.copy(),
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

    Only the episodes still running are stepped through the model; the per-step outputs are
    scattered back to full ``[B]`` rows, zero where an episode has already ended (those entries have
    mask 0). At B = 1 this is how a reference worker plays its episode (the ``async`` trainer)."""
    recorder = _LockstepRecorder(actor, noise, obs_keys, device)
    loop = EpisodeLoop(env, recorder, live_only=True)
    loop.start(np.arange(len(episodes)), episodes)
    loop.run(max_ticks=noise.shape[1])
    return recorder.trajectory(env)


def episode_losses(trajectory: Trajectory, config: A3CConfig) -> A3CLoss:
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


def accumulate_gradients(actor: Actor, trajectory: Trajectory, config: A3CConfig) -> A3CLoss:
    """Backpropagate the *mean* per-episode loss of the batch into ``.grad`` (the mean of the
    per-episode gradients, so one batched update moves as far as one reference update would with the
    average episode; at B = 1 it is exactly the reference's gradient)."""
    losses = episode_losses(trajectory, config)
    actor.backward(losses.total.mean())
    return losses
