"""Per-episode fast weights: each episode's own adapted parameters θ^b, which the model's
:meth:`~mapless.models.base.RecurrentNavModel.fast_step` steps with, and the learned loss's k-row
buffer. The two inner loops build on it: meta-training
(:class:`mapless.agent.meta.InnerLoop`, first and second order) and test-time adaptation
(:class:`mapless.agent.adaptation.TestTimeAdaptation`).

Representation of θ^b. The adaptive models are :class:`~mapless.models.base.RecurrentNavModel`:
encoder -> LSTMCell -> actor/critic heads.

* The LSTM matrices ``weight_ih`` (4H x D, ~6.5M entries) and ``weight_hh`` (4H x H) are never copied
  per episode: their inner gradient is a sum of outer products over the steps that used them,
  ``g_b = Σ_t δ_{b,t} [x_{b,t} || h_{b,t-1}]ᵀ`` with ``δ_{b,t} = ∂L_int^b/∂gates_{b,t}`` (BPTT included),
  so ``W^b [x || h] = W_0 [x || h] - α Σ_i Σ_t δ^{(i)}_{b,t} ([x^{(i)}_{b,t} || h^{(i)}_{b,t-1}] · [x || h])``:
  every inner step adds its k factors (``left = -α δ [B, k, 4H]``, ``right [B, k, D + H]``).
* Everything else that adapts (encoder, LSTM biases, actor) is small and is held per episode as a
  ``[B, ...]`` tensor. ``fast_step`` runs the encoder as ``vmap(functional_call(encoder, θ^b, ...))``
  and the LSTM and heads batched.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from mapless.agent.buffers import BufferPool
from mapless.agent.rollout_lstm import RolloutLstm
from mapless.models.base import LOW_RANK, ModelOutput, NavModel, RecurrentNavModel


@dataclass
class Step:
    """One forward step of the recurrent core, as needed for inner gradients of the LSTM matrices."""

    gates: Tensor  # [B_t, 4H] pre-activations (a graph node to differentiate w.r.t.)
    inputs: Tensor  # [B_t, D + H] = [x_t || h_{t-1}], the right factor of the step's gradient
    ids: Tensor  # [B_t] episode indices (into the batch given to start) of the rows
    updates: int  # inner steps taken before this step: it acted with θ_updates


@dataclass
class FastWeightState:
    """What both inner loops keep per batch of episodes."""

    #: per-episode ``[B, ...]`` adapted parameters (all but :data:`LOW_RANK`).
    fast: dict[str, Tensor]
    #: episode index (into the starting batch) of each current row, increasing.
    ids: Tensor
    #: θ_0's LSTM matrices for this batch.
    lstm: RolloutLstm
    #: the learned loss's rows ``[h_t || π_t]`` of the current chunk, each with the episode ids of
    #: its batch rows.
    rows: list[tuple[Tensor, Tensor]] = field(default_factory=list)
    #: the core steps since the last inner step (while more inner steps may come).
    chunk: list[Step] = field(default_factory=list)


class FastWeightForward:
    """An adaptive model run with per-episode fast weights (base of both inner loops)."""

    def __init__(
        self,
        model: NavModel,
        inner_lr: float | None = None,
        max_updates: int | None = None,
        dtype: torch.dtype | None = None,
    ):
        if not model.adaptive:
            raise TypeError(f"model {model.config.name!r} has no learned interaction loss")
        self.model = model
        self.inner_lr = model.inner_lr if inner_lr is None else inner_lr
        # k is fixed by the model: it is the TCN's input-channel count.
        self.steps = model.config.interaction_steps
        self.max_updates = model.config.max_inner_updates if max_updates is None else max_updates
        self.dtype = dtype  # compute dtype of the encoders and θ_0's LSTM products (agent/precision.py)
        self.names = model.inner_parameter_names()  # from the model's parameter roles
        if not isinstance(model, RecurrentNavModel) or not set(LOW_RANK) <= set(self.names):
            raise TypeError(f"model {model.config.name!r} is not an adaptive encoder-LSTM model")
        self.buffers = BufferPool()  # the LSTM operand and weight gradients, reused by every batch

    def _lstm(self, record: bool) -> RolloutLstm:
        return RolloutLstm(self.model.recurrent_cell, record=record, dtype=self.dtype, buffers=self.buffers)

    def _chunk_rows(self, state: FastWeightState, output: ModelOutput) -> Tensor | None:
        """Record the step's row ``[h_t || π_t]``; after k rows, the chunk's ``[B, k, H + 6]`` rows
        of the episodes still in the batch (the buffer starts again, as SAVN's does), else None."""
        row = torch.cat([output.hidden[0], torch.softmax(output.logits, dim=-1)], dim=-1)
        state.rows.append((row, state.ids))
        if len(state.rows) < self.steps:
            return None
        # Every episode still in the batch ran the whole chunk: its rows are in every step's batch.
        rows = torch.stack([align(r, ids, state.ids) for r, ids in state.rows], dim=1)
        state.rows = []
        return rows


def align(t: Tensor, ids: Tensor, current: Tensor) -> Tensor:
    """Rows of ``t`` (episodes ``ids``, increasing) for the episodes ``current`` (a subset of ids)."""
    if len(ids) == len(current):
        return t
    return t.index_select(0, torch.searchsorted(ids, current))
