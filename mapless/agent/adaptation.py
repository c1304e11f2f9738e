"""SAVN's inner loop at test time: every slot's fast weights adapt in place on the learned
interaction loss while θ and φ stay fixed (the evaluator's adaptive agent and PPO's whole-episode
acting, through :class:`mapless.agent.acting.AdaptingActor`).

The small fast weights are per-slot copies updated in place, and slot b's LSTM factors fill fixed
blocks (block i for its i-th inner step), so a slot is reset for a new episode by zeroing its blocks
(:meth:`TestTimeAdaptation.reset_slots`); memory per slot is ~0.5 MB instead of a copy of every
weight. The inner step is the training one (:class:`mapless.agent.meta.InnerLoop`) without a graph
to keep: the same fast weights follow from the same episode.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from mapless.agent.fast_weights import FastWeightForward, FastWeightState, Step
from mapless.agent.low_rank import apply_low_rank
from mapless.models.base import LOW_RANK, ModelOutput


@dataclass(kw_only=True)
class AdaptationState(FastWeightState):
    """Per-slot state (create with :meth:`TestTimeAdaptation.start`)."""

    #: fixed blocks of low-rank factors, ``-α δ [B, K, 4H]`` and ``[x || h] [B, K, D+H]``.
    left: Tensor
    right: Tensor
    #: inner steps taken by each slot's current episode.
    slot_updates: Tensor


class TestTimeAdaptation(FastWeightForward):
    """Batched test-time adaptation over ``B`` slots whose episodes start and end independently.

    Usage::

        adaptation = TestTimeAdaptation(model)
        state = adaptation.start(batch_size)
        adaptation.reset_slots(state, slots)  # new episodes there
        out = adaptation.forward(state, obs, hidden, prev_policy)
        ...  # sample actions, step the environments
        adaptation.observe(state, out, alive)  # every k steps the running slots adapt
    """

    __test__ = False  # its name starts with "Test": not a pytest class

    def start(self, batch_size: int) -> AdaptationState:
        params = dict(self.model.named_parameters())
        fast = {}
        for name in self.names:
            if name not in LOW_RANK:  # per-slot copies, updated and reset in place
                p = params[name].detach()
                fast[name] = p.unsqueeze(0).expand(batch_size, *p.shape).clone().requires_grad_()
        lstm = self._lstm(record=False)
        cell = lstm.cell
        ids = torch.arange(batch_size, device=lstm.device)
        columns = self.max_updates * self.steps
        gates, inputs = cell.weight_ih.shape[0], cell.input_size + cell.hidden_size
        return AdaptationState(
            fast=fast,
            ids=ids,
            lstm=lstm,
            left=cell.weight_ih.new_zeros(batch_size, columns, gates),
            right=cell.weight_ih.new_zeros(batch_size, columns, inputs),
            slot_updates=torch.zeros(batch_size, dtype=torch.long, device=ids.device),
        )

    def reset_slots(self, state: AdaptationState, slots: Tensor) -> None:
        """New episodes in ``slots`` start again from the trained θ."""
        params = dict(self.model.named_parameters())
        with torch.no_grad():
            for name, w in state.fast.items():
                w[slots] = params[name].detach()
            state.left[slots] = 0.0
            state.right[slots] = 0.0
            state.slot_updates[slots] = 0

    def forward(
        self,
        state: AdaptationState,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
    ) -> ModelOutput:
        """The model's forward pass with each slot's own fast weights."""
        if not state.chunk:
            # The fast weights are updated in place, so an inner step must not reach back into an
            # earlier chunk's graph (it acted with other weights): cut it at chunk starts.
            hidden, prev_policy = (hidden[0].detach(), hidden[1].detach()), prev_policy.detach()
        output, gates, inputs = self.model.fast_step(
            state.fast, obs, hidden, prev_policy, state.lstm, _low_rank_updates(state)
        )
        state.chunk.append(Step(gates, inputs, state.ids, 0))
        return output

    def value(
        self,
        state: AdaptationState,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
    ) -> Tensor:
        """``[B]`` V of ``obs`` under each slot's current fast weights, without recording a step (the
        value a time-limit truncation is bootstrapped with)."""
        with torch.no_grad():
            output = self.model.fast_step(
                state.fast, obs, hidden, prev_policy, state.lstm, _low_rank_updates(state)
            ).output
        return output.value.reshape(-1)

    def observe(self, state: AdaptationState, output: ModelOutput, alive: Tensor) -> None:
        """Record the step's row; after k rows the slots still running (``alive``) and under their
        episode's update limit take the inner step."""
        rows = self._chunk_rows(state, output)
        if rows is not None:
            self.adapt(state, rows, alive & (state.slot_updates < self.max_updates))

    def adapt(self, state: AdaptationState, rows: Tensor, due: Tensor) -> None:
        """One inner SGD step of the slots ``due``, in place (there is no meta-gradient to keep): the
        small fast weights are decremented (``α g`` rounded, then subtracted, as in training) and slot
        b's LSTM factors fill its block number ``slot_updates[b]``."""
        steps, state.chunk = state.chunk, []
        if not bool(due.any()):
            return
        loss = (self.model.learned_loss(rows) * due.to(rows.dtype)).sum()
        names = list(state.fast)
        grads = torch.autograd.grad(
            loss, [state.fast[n] for n in names] + [s.gates for s in steps], allow_unused=True
        )
        with torch.no_grad():
            for name, g in zip(names, grads[: len(names)], strict=True):
                if g is not None:  # out of the learned loss's reach: unchanged, as in SAVN
                    state.fast[name].sub_(g.mul_(self.inner_lr))
            slots = due.nonzero().squeeze(1)
            block = torch.arange(self.steps, device=slots.device)
            columns = state.slot_updates[slots, None] * self.steps + block
            delta = torch.stack(
                [
                    torch.zeros_like(s.gates) if g is None else g
                    for s, g in zip(steps, grads[len(names) :], strict=True)
                ],
                dim=1,
            )
            state.left[slots[:, None], columns] = -self.inner_lr * delta[slots]
            state.right[slots[:, None], columns] = torch.stack([s.inputs for s in steps], dim=1)[slots]
            state.slot_updates[slots] += 1


def _low_rank_updates(state: AdaptationState) -> Callable[[Tensor], Tensor]:
    """``[x || h]`` -> each slot's accumulated low-rank update of the LSTM gates."""
    return lambda inputs: apply_low_rank(inputs, state.left, state.right)
