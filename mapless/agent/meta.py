"""SAVN's meta-learning inner loop, batched over episodes with per-episode fast weights.

Within an episode, after every k interaction steps (k = 6, at most 4 times; never after the step that
ends the episode) the adapted parameters θ take one SGD step on the learned interaction loss:

    θ_{i+1} = θ_i - α ∇_θ L_int^φ(rows_i; θ_i),   rows_i = the last k rows [h_t || π_t] (acted with θ_i)

and the outer loss is the A3C loss of the whole episode, each step evaluated with the θ_i that acted
(the paper's eq. 3/5). Every episode b owns its fast weights θ^b; because episode b's interaction loss
depends only on θ^b, one ``autograd.grad`` of Σ_b L_int^b gives every episode's own gradient.

Representation of θ^b during training (``meta_train=True``). The adaptive models are
:class:`~mapless.models.base.RecurrentNavModel`: encoder -> LSTMCell -> actor/critic heads.

* The LSTM matrices ``weight_ih`` (4H x D, ~6.5M entries) and ``weight_hh`` (4H x H) are never copied
  per episode: their inner gradient is a sum of outer products over the steps that used them,
  ``g_b = Σ_t δ_{b,t} [x_{b,t} || h_{b,t-1}]ᵀ`` with ``δ_{b,t} = ∂L_int^b/∂gates_{b,t}`` (BPTT included),
  so ``W^b [x || h] = W_0 [x || h] - α Σ_i Σ_t δ^{(i)}_{b,t} ([x^{(i)}_{b,t} || h^{(i)}_{b,t-1}] · [x || h])``.
  Each inner step appends its k factors (``left = -α δ [B, k, 4H]``, ``right [B, k, D + H]``), and
  the δ come from ``autograd.grad`` w.r.t. the recorded gate pre-activations (with ``create_graph``
  for second order), so the values and every derivative are those of the materialised update; only
  the floating-point summation order differs.
* Everything else that adapts (encoder, LSTM biases, actor) is small and is materialised per episode
  as a ``[B, ...]`` tensor, starting as a broadcast view of θ_0. The encoder runs as
  ``vmap(functional_call(encoder, θ^b, ...))``, the LSTM and heads run batched.

Meta-gradients (:meth:`InnerLoop.backward`):

* ``second_order`` (default, SAVN): backpropagate the outer loss through every inner step
  (``create_graph=True``); θ_0 receives ``Π(I - α H_int) ∇L_nav`` terms and φ receives gradient only
  through the inner steps.
* ``first_order`` (the first-order Taylor form, eq. 4: L_nav(θ) - α <∇L_int^φ(θ), ∇L_nav(θ)>): the
  fast weights follow the same trajectory but the inner step is a constant shift for θ_0 (its gradient
  is the sum of the outer loss's partial derivatives w.r.t. every θ_i), and φ receives the gradient of
  the inner-product term, ``-α Σ_i (∂g_i/∂φ)ᵀ v_i`` with ``v_i = ∂L_nav/∂θ_{i+1}`` held constant. For
  the low-rank matrices ``v_i = Σ_{t after step i} Δ_t r_tᵀ`` (``Δ_t = ∂L_nav/∂gates_t``), so
  ``<g_i, v_i> = Σ_{s,t} (δ_s · Δ_t)(r_s · r_t)`` needs no matrix either. For a single inner step this
  differs from second order only by ``-α H_int v`` on θ_0 (the φ gradients are equal);
  tests/test_meta.py checks exactly that.

At test time (``meta_train=False``) the same inner steps run with φ frozen and no outer graph: the
small fast weights are per-slot copies updated in place, and slot b's LSTM factors fill fixed blocks
(block i for its i-th inner step), so the evaluator resets a slot for a new episode by zeroing its
blocks (:meth:`InnerLoop.reset_slots`); memory per slot is ~0.5 MB instead of a copy of every weight.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.func import functional_call, vmap

from mapless.agent.buffers import BufferPool
from mapless.agent.low_rank import LowRankUpdates, apply_low_rank
from mapless.agent.precision import encoder_autocast, like
from mapless.agent.rollout_lstm import RolloutLstm, accumulate_grad
from mapless.models.base import ModelOutput, NavModel, RecurrentNavModel, lstm_state_from_gates

#: LSTM matrices (of :attr:`RecurrentNavModel.lstm`) whose per-episode updates are kept in low rank.
LOW_RANK = ("lstm.weight_ih", "lstm.weight_hh")


@dataclass
class _Step:
    """One forward step of the recurrent core, as needed for inner gradients of the LSTM matrices."""

    gates: Tensor  # [B_t, 4H] pre-activations (a graph node to differentiate w.r.t.)
    inputs: Tensor  # [B_t, D + H] = [x_t || h_{t-1}], the right factor of the step's gradient
    ids: Tensor  # [B_t] episode indices (into the batch given to start) of the rows
    updates: int  # inner steps taken before this step: it acted with θ_updates


@dataclass
class InnerLoopState:
    """Per-batch state of one lockstep rollout of B episodes (create with :meth:`InnerLoop.start`)."""

    #: per-episode ``[B, ...]`` adapted parameters (training: all but :data:`LOW_RANK`).
    fast: dict[str, Tensor]
    #: the learned loss's rows ``[h_t || π_t]`` of the current chunk, each with the episode ids of
    #: its batch rows.
    rows: list[tuple[Tensor, Tensor]] = field(default_factory=list)
    updates: int = 0
    #: first order only: (inner gradients g_i, fast weights θ_{i+1}) of every inner step.
    records: list[tuple[dict[str, Tensor], dict[str, Tensor]]] = field(default_factory=list)
    #: training: episode index (into the starting batch) of each current row, increasing.
    ids: Tensor | None = None
    #: training: per adapted parameter, the tensors the current chunk's steps read it from, each with
    #: its episode ids: ``fast`` as the chunk began, and the fresh views of θ_0 that a compaction of
    #: a still-unadapted (broadcast) parameter makes. The inner step differentiates with respect to
    #: them; a compacted copy of an adapted one is a row selection of its source, so it adds none.
    sources: dict[str, list[tuple[Tensor, Tensor]]] = field(default_factory=dict)
    batch_size: int = 0  # B at start
    #: training: low-rank updates of the LSTM matrices, ``-α δ [B, K, 4H]`` and ``[x || h] [B, K, D+H]``.
    left: Tensor | None = None
    right: Tensor | None = None
    #: training: the steps' view of left/right (None until the first inner step; test time: None).
    low_rank: LowRankUpdates | None = None
    #: training: the core steps since the last inner step (while more inner steps may come).
    chunk: list[_Step] = field(default_factory=list)
    #: first order only: per inner step (δ with its graph to φ, [x || h], ids), and every step after
    #: the first inner step (their Δ_t = ∂L_nav/∂gates_t give v_i in :meth:`InnerLoop.backward`).
    factor_records: list[tuple[Tensor, Tensor, Tensor]] = field(default_factory=list)
    later_steps: list[_Step] = field(default_factory=list)
    #: θ_0's LSTM matrices for this rollout (in training their gradient is computed once, at the end).
    lstm: RolloutLstm | None = None
    #: test time: inner steps taken by each slot's current episode.
    slot_updates: Tensor | None = None


class _Encoder(nn.Module):
    """``model.encode`` (after ``model.describe`` unless that runs outside) as a module's forward, so
    that ``functional_call`` can swap its weights."""

    def __init__(self, model: RecurrentNavModel, describe: bool):
        super().__init__()
        self.model = model
        self.describe = describe

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        described = self.model.describe(obs) if self.describe else obs
        return self.model.encode(described, hidden, prev_policy)


class InnerLoop:
    """Functional, batched SAVN inner loop around an adaptive model (savn, gve, spatt, cvmeta).

    Usage per lockstep batch of episodes::

        loop = InnerLoop(model)
        state = loop.start(batch_size)
        for t in range(T):
            out = loop.forward(state, obs, hidden, prev_policy)
            ...  # sample actions, step the environments
            loop.observe(state, out, alive)  # alive [B] bool: episode not ended by this step
            # optionally, between chunks of k steps: loop.compact(state, keep)
        loop.backward(state, a3c_loss(...).total.mean())  # the trainer averages episodes
    """

    def __init__(
        self,
        model: NavModel,
        inner_lr: float | None = None,
        max_updates: int | None = None,
        first_order: bool = False,
        meta_train: bool = True,
        dtype: torch.dtype | None = None,
    ):
        if not model.adaptive:
            raise TypeError(f"model {model.config.name!r} has no learned interaction loss")
        self.model = model
        self.inner_lr = model.inner_lr if inner_lr is None else inner_lr
        # k is fixed by the model: it is the TCN's input-channel count.
        self.steps = model.config.interaction_steps
        self.max_updates = model.config.max_inner_updates if max_updates is None else max_updates
        self.first_order = first_order
        self.meta_train = meta_train
        self.dtype = dtype  # compute dtype of the encoders and θ_0's LSTM products (agent/precision.py)
        self.names = model.inner_parameter_names()  # from the model's parameter roles
        if not isinstance(model, RecurrentNavModel) or not set(LOW_RANK) <= set(self.names):
            raise TypeError(f"model {model.config.name!r} is not an adaptive encoder-LSTM model")
        # Adapted parameters of the batched recurrent core, kept out of the vmapped encoder's call.
        self._core = set(model.core_parameter_names())
        # Under adapt: policy, describe() reads θ_0 only: one batched call instead of B under vmap.
        self._describe_batched = model.adapts_policy_only
        self._encoder = _Encoder(model, describe=not self._describe_batched)
        self.buffers = BufferPool()  # the LSTM operand and weight gradients, reused by every rollout

    # -- rollout -------------------------------------------------------------------------------
    def start(self, batch_size: int) -> InnerLoopState:
        params = dict(self.model.named_parameters())
        fast = {}
        for name in self.names:
            p = params[name]
            if name in LOW_RANK:
                continue
            if self.meta_train:
                # A broadcast view: differentiable back to θ_0, no copy until the first update.
                fast[name] = p.unsqueeze(0).expand(batch_size, *p.shape)
            else:  # per-slot copies, updated and reset in place
                fast[name] = p.detach().unsqueeze(0).expand(batch_size, *p.shape).clone().requires_grad_()
        cell = self.model.lstm
        lstm = RolloutLstm(cell, record=self.meta_train, dtype=self.dtype, buffers=self.buffers)
        ids = torch.arange(batch_size, device=cell.weight_ih.device)
        state = InnerLoopState(fast=fast, ids=ids, batch_size=batch_size, lstm=lstm)
        state.sources = {name: [(w, ids)] for name, w in fast.items()}
        if not self.meta_train:
            # Fixed per-slot blocks of low-rank factors: slot b's i-th inner step writes block i.
            columns = self.max_updates * self.steps
            gates, inputs = cell.weight_ih.shape[0], cell.input_size + cell.hidden_size
            state.left = cell.weight_ih.new_zeros(batch_size, columns, gates)
            state.right = cell.weight_ih.new_zeros(batch_size, columns, inputs)
            state.slot_updates = torch.zeros(batch_size, dtype=torch.long, device=ids.device)
        return state

    def reset_slots(self, state: InnerLoopState, slots: Tensor) -> None:
        """Test time: new episodes in ``slots`` start again from the trained θ."""
        params = dict(self.model.named_parameters())
        with torch.no_grad():
            for name, w in state.fast.items():
                w[slots] = params[name].detach()
            state.left[slots] = 0.0
            state.right[slots] = 0.0
            state.slot_updates[slots] = 0

    def forward(
        self,
        state: InnerLoopState,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
    ) -> ModelOutput:
        """The model's forward pass with each episode's own fast weights."""
        model = self.model
        if not self.meta_train and not state.chunk:
            # Test time: the fast weights are updated in place, so an inner step must not reach back
            # into an earlier chunk's graph (it acted with other weights): cut it at chunk starts.
            hidden, prev_policy = (hidden[0].detach(), hidden[1].detach()), prev_policy.detach()
        encoder_fast = {f"model.{n}": w for n, w in state.fast.items() if n not in self._core}

        def one_episode(fast, episode_obs, h, c, policy):
            single = {key: value.unsqueeze(0) for key, value in episode_obs.items()}
            x, extra = functional_call(
                self._encoder, fast, (single, (h.unsqueeze(0), c.unsqueeze(0)), policy.unsqueeze(0))
            )
            return (x[0],) if extra is None else (x[0], extra[0])

        with encoder_autocast(self.dtype, prev_policy.device):
            if self._describe_batched:
                obs = model.describe(obs)
            encoded = vmap(one_episode, randomness="different")(
                encoder_fast, obs, hidden[0], hidden[1], prev_policy
            )
        x, extra = like(encoded[0], hidden[0]), (like(encoded[1], hidden[0]) if len(encoded) > 1 else None)

        # The LSTM cell of base.lstm_step, with θ_0's matrices plus the episodes' low-rank updates.
        h_prev, c_prev = hidden
        inputs, product = state.lstm.gates(x, h_prev)
        gates = product + self._param(state, "lstm.bias_ih") + self._param(state, "lstm.bias_hh")
        if state.low_rank is not None:  # training
            gates = gates + state.low_rank(inputs)
        elif state.left is not None:  # test time: the slots' fixed blocks
            gates = gates + apply_low_rank(inputs, state.left, state.right)
        h, c = lstm_state_from_gates(gates, c_prev)

        weight = self._param(state, "actor_linear.weight")
        if weight.dim() == 3:
            logits = torch.einsum("bh,bah->ba", h, weight) + self._param(state, "actor_linear.bias")
        else:
            logits = F.linear(h, weight, self._param(state, "actor_linear.bias"))

        step = _Step(gates, inputs, state.ids, state.updates)
        if state.updates < self.max_updates or not self.meta_train:
            state.chunk.append(step)
        if self.first_order and state.updates > 0:
            state.later_steps.append(step)
        return ModelOutput(logits, model.value(h, extra), (h, c))

    def _param(self, state: InnerLoopState, name: str) -> Tensor:
        """Per-episode ``[B, ...]`` fast weight, or θ_0 when the inner step does not adapt ``name``."""
        return state.fast[name] if name in state.fast else self.model.get_parameter(name)

    def observe(self, state: InnerLoopState, output: ModelOutput, alive: Tensor) -> None:
        """Record the step's row ``[h_t || π_t]``; after k rows take the inner step for the episodes
        still running (``alive``), up to the update limit (training: per rollout; test time: per
        slot's episode)."""
        row = torch.cat([output.hidden[0], torch.softmax(output.logits, dim=-1)], dim=-1)
        state.rows.append((row, state.ids))
        if len(state.rows) < self.steps:
            return
        # Every episode still in the batch ran the whole chunk: its rows are in every step's batch.
        rows = torch.stack([_align(r, ids, state.ids) for r, ids in state.rows], dim=1)
        state.rows = []  # SAVN resets the learned-loss buffer after every chunk of k
        if not self.meta_train:
            self.adapt(state, rows, alive & (state.slot_updates < self.max_updates))
        elif state.updates < self.max_updates and bool(alive.any()):
            self.adapt(state, rows, alive)

    def compact(self, state: InnerLoopState, keep: Tensor) -> None:
        """Keep only the rows ``keep`` (increasing indices into the current batch) of ``state``
        (training only), at any step. Dropped episodes must never adapt again and must not contribute
        to the outer loss after this point. Recorded steps and rows keep their tensors (their ``ids``
        say which episodes their rows are); the next inner step differentiates with respect to the
        chunk's :attr:`InnerLoopState.sources`, so the gradient of every row of the chunk, before
        and after this call, reaches the episode's fast weights."""
        if not self.meta_train:
            raise RuntimeError("compact() is for training rollouts (test time resets slots instead)")
        state.ids = state.ids.index_select(0, keep)
        params = dict(self.model.named_parameters())
        for name, w in state.fast.items():
            if w.dim() > 0 and w.stride(0) == 0:  # still θ_0 for every episode: a new view, no copy
                # (a slice of the old view would send every episode's inner gradient to its row 0)
                state.fast[name] = params[name].unsqueeze(0).expand(len(keep), *w.shape[1:])
                state.sources[name].append((state.fast[name], state.ids))
            else:
                state.fast[name] = w.index_select(0, keep)
        if state.left is not None:
            self._set_low_rank(state, state.left.index_select(0, keep), state.right.index_select(0, keep))

    # -- inner step ----------------------------------------------------------------------------
    def adapt(self, state: InnerLoopState, rows: Tensor, active: Tensor) -> None:
        """One inner SGD step of the episodes where ``active`` (``[B]`` bool) on ``rows [B, k, H+6]``."""
        if not self.meta_train:
            self._adapt_in_place(state, rows, active)
            return
        loss = (self.model.learned_loss(rows) * active.to(rows.dtype)).sum()
        names = list(state.fast)
        steps = state.chunk
        # create_graph: second order differentiates through the step; first order needs g_i's graph to φ.
        sources = [(name, w, ids) for name in names for w, ids in state.sources[name]]
        grads = torch.autograd.grad(
            loss,
            [w for _, w, _ in sources] + [s.gates for s in steps],
            create_graph=True,
            allow_unused=True,
        )
        inner: dict[str, Tensor] = {}  # per-episode gradients, rows of the current batch
        for (name, _, ids), g in zip(sources, grads[: len(sources)], strict=True):
            if g is not None:
                g = _align(g, ids, state.ids)
                inner[name] = g if name not in inner else inner[name] + g
        new_fast, used = {}, {}
        for name in names:
            w, g = state.fast[name], inner.get(name)
            if g is None:  # parameter outside the learned loss's reach: unchanged (SAVN)
                new_fast[name] = w
            elif self.first_order:
                new_fast[name] = w - self.inner_lr * g.detach()
                used[name] = g
            else:
                new_fast[name] = w - self.inner_lr * g
        self._append_low_rank(state, steps, grads[len(sources) :])
        if self.first_order:
            state.records.append((used, {n: new_fast[n] for n in used}))
        state.fast = new_fast
        state.sources = {name: [(w, state.ids)] for name, w in new_fast.items()}
        state.updates += 1

    def _adapt_in_place(self, state: InnerLoopState, rows: Tensor, due: Tensor) -> None:
        """Test time: the same step for the slots ``due``, in place (there is no meta-gradient to
        keep): the small fast weights are decremented (``α g`` rounded, then subtracted, as in
        training) and slot b's LSTM factors fill its block number ``slot_updates[b]``."""
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

    def _append_low_rank(
        self, state: InnerLoopState, steps: list[_Step], grads: tuple[Tensor | None, ...]
    ) -> None:
        """Add this inner step's factors of the LSTM matrices' update (``δ`` and ``[x || h]``)."""
        deltas, inputs = [], []
        for step, g in zip(steps, grads, strict=True):
            g = torch.zeros_like(step.gates) if g is None else g
            deltas.append(_align(g, step.ids, state.ids))
            inputs.append(_align(step.inputs, step.ids, state.ids))
        delta, right = torch.stack(deltas, dim=1), torch.stack(inputs, dim=1)
        if self.first_order:
            state.factor_records.append((delta, right.detach(), state.ids))
            delta, right = delta.detach(), right.detach()  # a constant shift for θ_0
        left = -self.inner_lr * delta
        if state.left is not None:
            left, right = torch.cat([state.left, left], dim=1), torch.cat([state.right, right], dim=1)
        self._set_low_rank(state, left, right)
        state.chunk = []

    @staticmethod
    def _set_low_rank(state: InnerLoopState, left: Tensor, right: Tensor) -> None:
        """New factors for the steps to come (their gradients are summed once, mapless.agent.low_rank)."""
        state.low_rank = LowRankUpdates(left, right)
        state.left, state.right = state.low_rank.left, state.low_rank.right

    # -- meta-gradient -------------------------------------------------------------------------
    def backward(self, state: InnerLoopState, loss: Tensor) -> None:
        """Accumulate the meta-gradient of the outer ``loss`` (a scalar) into ``.grad`` of θ_0 and φ."""
        if not self.meta_train:
            raise RuntimeError("backward() needs an InnerLoop built with meta_train=True")
        params = [(n, p) for n, p in self.model.named_parameters() if p.requires_grad]
        if not self.first_order:
            grads = state.lstm.grad(loss, [p for _, p in params])
            accumulate_grad([p for _, p in params], grads, adopt=state.lstm.weight_gradients)
            return
        phi = set(self.model.learned_loss_parameter_names())
        theta = [(n, p) for n, p in params if n not in phi]
        shifted = [t for _, after in state.records for t in after.values()]
        later = state.later_steps if state.factor_records else []
        grads = state.lstm.grad(
            loss, [p for _, p in theta] + shifted + [s.gates for s in later], retain_graph=bool(state.records)
        )
        accumulate_grad([p for _, p in theta], grads[: len(theta)], adopt=state.lstm.weight_gradients)
        if not state.records:
            return
        # Eq. 4's inner-product term: only φ is differentiated (θ_0's share is the dropped Hessian term).
        v = iter(grads[len(theta) : len(theta) + len(shifted)])
        inner = loss.new_zeros(())
        for used, _after in state.records:
            for g in used.values():
                vi = next(v)
                if vi is not None:
                    inner = inner + (g * vi.detach()).sum()
        if later:
            inner = inner + _low_rank_inner_product(state, later, grads[len(theta) + len(shifted) :])
        phi_params = [p for n, p in params if n in phi]
        if inner.requires_grad:
            phi_grads = torch.autograd.grad(-self.inner_lr * inner, phi_params, allow_unused=True)
            accumulate_grad(phi_params, phi_grads)


def _low_rank_inner_product(
    state: InnerLoopState, later: list[_Step], outer: tuple[Tensor | None, ...]
) -> Tensor:
    """``Σ_i <g_i, v_i>`` of the LSTM matrices in factored form: ``g_i = Σ_s δ_s r_sᵀ`` and
    ``v_i = Σ_{t acted with θ_{i+1} or later} Δ_t r_tᵀ``, so ``<g_i, v_i> = Σ_{s,t} (δ_s·Δ_t)(r_s·r_t)``
    per episode (rows of different batch sizes are matched through their episode ids)."""
    total = later[0].gates.new_zeros(())
    size = state.batch_size
    outer_d = torch.stack(
        [
            _scatter(torch.zeros_like(s.gates) if d is None else d, s.ids, size)
            for s, d in zip(later, outer, strict=True)
        ],
        dim=1,
    ).detach()
    outer_r = torch.stack([_scatter(s.inputs.detach(), s.ids, size) for s in later], dim=1)
    acted = torch.tensor([s.updates for s in later], device=outer_d.device)
    for i, (delta, right, ids) in enumerate(state.factor_records):
        after = acted > i  # steps that used θ_{i+1} or a later θ (θ_{j+1} = θ_j - α g_j.detach())
        if not bool(after.any()):
            continue
        deltas = torch.einsum("bso,bto->bst", _scatter(delta, ids, size), outer_d[:, after])
        inputs = torch.einsum("bsd,btd->bst", _scatter(right, ids, size), outer_r[:, after])
        total = total + (deltas * inputs).sum()
    return total


def _align(t: Tensor, ids: Tensor, current: Tensor) -> Tensor:
    """Rows of ``t`` (episodes ``ids``, increasing) for the episodes ``current`` (a subset of ids)."""
    if len(ids) == len(current):
        return t
    return t.index_select(0, torch.searchsorted(ids, current))


def _scatter(t: Tensor, ids: Tensor, size: int) -> Tensor:
    """``t``'s rows placed at ``ids`` in a zero tensor of ``size`` rows (differentiable in ``t``)."""
    if len(ids) == size:
        return t
    return t.new_zeros(size, *t.shape[1:]).index_copy(0, ids, t)
