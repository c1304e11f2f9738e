"""Per-episode fast weights: each episode's own adapted parameters θ^b, which the model's
:meth:`~mapless.models.base.RecurrentNavModel.fast_step` steps with, and the learned loss's k-row
buffer. The two inner loops build on it, both in :mod:`mapless.agent.meta`: meta-training
(:class:`~mapless.agent.meta.InnerLoop`, first and second order) and test-time adaptation
(:class:`~mapless.agent.meta.TestTimeAdaptation`).

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

The low-rank updates of the LSTM matrices, with the gradients of their factors summed once
(:class:`LowRankUpdates`). After i inner steps, episode b's LSTM matrices are
``W_0 + Σ_k left[b, k]ᵀ right[b, k]`` (``left`` ``[B, K, 4H]``, ``right`` ``[B, K, D + H]``), so a
step adds ``(right · x) · left`` to the gates of its input row x. Plain autograd differentiates that
per step: every step's backward forms full ``[B, K, D + H]`` and ``[B, K, 4H]`` outer products for the
two factors and adds them up, and so does every inner step's backward product (second order). At
B = 256 that is ~140 MB of writes per step, a sixth of a cvmeta update in profiles. Their sum is one
batched product of the stacked per-step vectors, so here

* the factors enter the steps through an anchor node (:class:`_Anchor`), which autograd runs after
  every step that used them;
* the steps (:class:`_Apply`) and the inner steps' backward products (:class:`_ApplyTransposed`)
  return no gradient for the factors in the outer backward and record their two vectors instead;
* the anchor's backward turns the records into the factors' gradients with one ``bmm`` each.

Where a backward is itself differentiated (an inner step under ``create_graph``) the plain
gradients are returned, so derivatives of every order stay exact (tests/test_meta.py compares the
meta-gradients with hand-unrolled autograd).
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


def apply_low_rank(inputs: Tensor, left: Tensor, right: Tensor) -> Tensor:
    """``(right · inputs) · left``: ``[B, D + H]`` -> ``[B, 4H]`` (plain autograd)."""
    return torch.einsum("bk,bko->bo", torch.einsum("bkd,bd->bk", right, inputs), left)


class _Records:
    """Per-step vector pairs whose outer products sum to a factor's gradient. Holds plain tensors
    only (made in a backward without graph), so the autograd nodes can own it without a cycle."""

    def __init__(self) -> None:
        self.left: list[tuple[Tensor, Tensor]] = []  # ([B, K], [B, 4H])
        self.right: list[tuple[Tensor, Tensor]] = []  # ([B, K], [B, D + H])


def _sum_of_outer_products(pairs: list[tuple[Tensor, Tensor]]) -> Tensor:
    """``Σ_t a_t[b]ᵀ v_t[b]`` for every b: ``[B, K, X]`` from pairs ``([B, K], [B, X])``."""
    coefficients = torch.stack([a for a, _ in pairs], dim=2)  # [B, K, T]
    vectors = torch.stack([v for _, v in pairs], dim=1)  # [B, T, X]
    return torch.bmm(coefficients, vectors)


class _Anchor(torch.autograd.Function):
    """Identity on the factors; its backward adds the recorded outer products to whatever gradient
    arrives through ordinary ops (a later concatenation or row selection)."""

    @staticmethod
    def forward(ctx, left: Tensor, right: Tensor, records: _Records) -> tuple[Tensor, Tensor]:
        ctx.set_materialize_grads(False)
        ctx.records = records
        return left.view_as(left), right.view_as(right)

    @staticmethod
    def backward(ctx, grad_left: Tensor | None, grad_right: Tensor | None) -> tuple:
        records = ctx.records
        if records.left:
            deferred = _sum_of_outer_products(records.left)
            grad_left = deferred if grad_left is None else grad_left + deferred
        if records.right:
            deferred = _sum_of_outer_products(records.right)
            grad_right = deferred if grad_right is None else grad_right + deferred
        records.left, records.right = [], []  # a retained graph's next backward starts afresh
        return grad_left, grad_right, None


class _Apply(torch.autograd.Function):
    """``(right · inputs) · left`` of one step (see the module docstring)."""

    @staticmethod
    def forward(ctx, inputs: Tensor, left: Tensor, right: Tensor, records: _Records) -> Tensor:
        coefficients = torch.einsum("bkd,bd->bk", right, inputs)
        ctx.save_for_backward(inputs, left, right, coefficients)
        ctx.records = records
        return torch.einsum("bk,bko->bo", coefficients, left)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple:
        inputs, left, right, coefficients = ctx.saved_tensors
        need_inputs, need_left, need_right = ctx.needs_input_grad[:3]
        grad_inputs = grad_left = grad_right = None
        if torch.is_grad_enabled():  # differentiated again (an inner step): plain, exact gradients
            if need_inputs:
                grad_inputs = _ApplyTransposed.apply(grad, left, right, ctx.records)
            if need_left or need_right:
                coefficients = torch.einsum("bkd,bd->bk", right, inputs)
                by_column = torch.einsum("bo,bko->bk", grad, left)
                grad_left = coefficients.unsqueeze(-1) * grad.unsqueeze(1) if need_left else None
                grad_right = by_column.unsqueeze(-1) * inputs.unsqueeze(1) if need_right else None
            return grad_inputs, grad_left, grad_right, None
        by_column = torch.einsum("bo,bko->bk", grad, left)
        if need_inputs:
            grad_inputs = torch.einsum("bk,bkd->bd", by_column, right)
        if need_left:
            ctx.records.left.append((coefficients, grad))
        if need_right:
            ctx.records.right.append((by_column, inputs))
        return grad_inputs, None, None, None


class _ApplyTransposed(torch.autograd.Function):
    """``(left · grad) · right``: the gradient of :class:`_Apply` with respect to its inputs, as an
    inner step computes it under ``create_graph`` (so that the outer backward defers its factors'
    share too)."""

    @staticmethod
    def forward(ctx, grad: Tensor, left: Tensor, right: Tensor, records: _Records) -> Tensor:
        ctx.save_for_backward(grad, left, right)
        ctx.records = records
        return torch.einsum("bk,bkd->bd", torch.einsum("bo,bko->bk", grad, left), right)

    @staticmethod
    def backward(ctx, upstream: Tensor) -> tuple:
        grad, left, right = ctx.saved_tensors
        need_grad, need_left, need_right = ctx.needs_input_grad[:3]
        by_column = torch.einsum("bd,bkd->bk", upstream, right)  # ∂/∂(left · grad)
        grad_grad = torch.einsum("bk,bko->bo", by_column, left) if need_grad else None
        if torch.is_grad_enabled():
            along = torch.einsum("bo,bko->bk", grad, left)
            grad_left = by_column.unsqueeze(-1) * grad.unsqueeze(1) if need_left else None
            grad_right = along.unsqueeze(-1) * upstream.unsqueeze(1) if need_right else None
            return grad_grad, grad_left, grad_right, None
        if need_left:
            ctx.records.left.append((by_column, grad))
        if need_right:
            ctx.records.right.append((torch.einsum("bo,bko->bk", grad, left), upstream))
        return grad_grad, None, None, None


class LowRankUpdates:
    """The factors of one stretch of steps (until the next inner step or row selection changes
    them). ``left`` and ``right`` are the anchored tensors to build the next factors from."""

    def __init__(self, left: Tensor, right: Tensor):
        self._records = _Records()
        self.deferred = left.requires_grad or right.requires_grad
        if self.deferred:
            left, right = _Anchor.apply(left, right, self._records)
        self.left, self.right = left, right

    def __call__(self, inputs: Tensor) -> Tensor:
        """The updates' contribution to the gates of the input rows ``[B, D + H]``."""
        if not self.deferred:
            return apply_low_rank(inputs, self.left, self.right)
        return _Apply.apply(inputs, self.left, self.right, self._records)
