"""SAVN's meta-learning inner loop, batched over episodes with per-episode fast weights.

Within an episode, after every k interaction steps (``model.interaction_steps``, k = 6; at most
``model.max_inner_updates`` = 4 times; never after the step that ends the episode) the adapted
parameters θ take one SGD step on the learned interaction loss:

    θ_{i+1} = θ_i - α ∇_θ L_int^φ(rows_i; θ_i),   rows_i = the last k rows [h_t || π_t] (acted with θ_i)

and the trainer's outer loss reads the episode's steps, each evaluated with the θ_i that acted. That
is SAVN's code. The paper's eq. 3/5 writes one adaptation after the first k steps and the navigation
loss on the rest of the trajectory: ``max_inner_updates = 1`` here, with the trainer's outer loss
restricted to the steps after the first k (PPO's ``ppo.meta.navigation_loss: after_interaction``).
Every episode b owns its fast weights θ^b; because episode b's interaction loss depends only on θ^b,
one ``autograd.grad`` of Σ_b L_int^b gives every episode's own gradient.

Representation of θ^b (:mod:`mapless.agent.fast_weights`): the LSTM matrices' per-episode updates
in low rank, the δ from ``autograd.grad`` w.r.t. the recorded gate pre-activations (with
``create_graph`` for second order), so the values and every derivative are those of the materialised
update; only the floating-point summation order differs. The other adapted parameters start as a
broadcast view of θ_0 (no copy until the first update).

Meta-gradients (:meth:`InnerLoop.backward`):

* ``second_order`` (default, SAVN; the exact gradient of eq. 3/5): backpropagate the outer loss through every inner step
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

At test time (:class:`TestTimeAdaptation`: the evaluator's adaptive agent and PPO's whole-episode
acting, through :class:`mapless.agent.acting.AdaptingActor`) the same inner step runs without a graph
to keep, while θ and φ stay fixed: the same fast weights follow from the same episode. The small fast
weights are per-slot copies updated in place, and slot b's LSTM factors fill fixed blocks (block i for
its i-th inner step), so a slot is reset for a new episode by zeroing its blocks
(:meth:`TestTimeAdaptation.reset_slots`); memory per slot is ~0.5 MB instead of a copy of every
weight.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from mapless.agent.fast_weights import (
    FastWeightForward,
    FastWeightState,
    LowRankUpdates,
    Step,
    align,
    apply_low_rank,
)
from mapless.agent.rollout_lstm import accumulate_grad
from mapless.models.base import LOW_RANK, FastStep, ModelOutput, NavModel
from mapless.models.layers import scatter_rows


@dataclass
class InnerLoopState(FastWeightState):
    """Per-batch state of one lockstep rollout of B episodes (create with :meth:`InnerLoop.start`)."""

    updates: int = 0
    #: first order only: (inner gradients g_i, fast weights θ_{i+1}) of every inner step.
    records: list[tuple[dict[str, Tensor], dict[str, Tensor]]] = field(default_factory=list)
    #: per adapted parameter, the tensors the current chunk's steps read it from, each with its
    #: episode ids: ``fast`` as the chunk began, and the fresh views of θ_0 that a compaction of a
    #: still-unadapted (broadcast) parameter makes. The inner step differentiates with respect to
    #: them; a compacted copy of an adapted one is a row selection of its source, so it adds none.
    sources: dict[str, list[tuple[Tensor, Tensor]]] = field(default_factory=dict)
    batch_size: int = 0  # B at start
    #: low-rank updates of the LSTM matrices, ``-α δ [B, K, 4H]`` and ``[x || h] [B, K, D+H]``.
    left: Tensor | None = None
    right: Tensor | None = None
    #: the steps' view of left/right (None until the first inner step).
    low_rank: LowRankUpdates | None = None
    #: first order only: per inner step (δ with its graph to φ, [x || h], ids), and every step after
    #: the first inner step (their Δ_t = ∂L_nav/∂gates_t give v_i in :meth:`InnerLoop.backward`).
    factor_records: list[tuple[Tensor, Tensor, Tensor]] = field(default_factory=list)
    later_steps: list[Step] = field(default_factory=list)


class InnerLoop(FastWeightForward):
    """Functional, batched SAVN inner loop for meta-training an adaptive model (savn, gve, spatt,
    cvmeta).

    Usage per lockstep batch of episodes::

        loop = InnerLoop(model)
        state = loop.start(batch_size)
        for t in range(T):
            out = loop.forward(state, obs, hidden, prev_policy)
            ...  # sample actions, step the environments
            loop.observe(state, out, alive)  # alive [B] bool: episode not ended by this step
            # optionally, at any step: loop.compact(state, keep)
        loop.backward(state, a3c_loss(...).total.mean())  # the trainer averages episodes
    """

    def __init__(
        self,
        model: NavModel,
        inner_lr: float | None = None,
        max_updates: int | None = None,
        first_order: bool = False,
        dtype: torch.dtype | None = None,
    ):
        super().__init__(model, inner_lr, max_updates, dtype)
        self.first_order = first_order

    # -- rollout -------------------------------------------------------------------------------
    def start(self, batch_size: int) -> InnerLoopState:
        params = dict(self.model.named_parameters())
        # Broadcast views: differentiable back to θ_0, no copy until the first update.
        fast = {
            name: params[name].unsqueeze(0).expand(batch_size, *params[name].shape)
            for name in self.names
            if name not in LOW_RANK
        }
        lstm = self._lstm(record=True)
        ids = torch.arange(batch_size, device=lstm.device)
        state = InnerLoopState(fast=fast, ids=ids, lstm=lstm, batch_size=batch_size)
        state.sources = {name: [(w, ids)] for name, w in fast.items()}
        return state

    def forward(
        self,
        state: InnerLoopState,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
    ) -> ModelOutput:
        """The model's forward pass with each episode's own fast weights."""
        return self._record(
            state, self.model.fast_step(state.fast, obs, hidden, prev_policy, state.lstm, state.low_rank)
        )

    def _record(self, state: InnerLoopState, fast_step: FastStep) -> ModelOutput:
        """Keep the step's gates and LSTM input for the inner steps (and first order's backward)."""
        output, gates, inputs = fast_step
        step = Step(gates, inputs, state.ids, state.updates)
        if state.updates < self.max_updates:
            state.chunk.append(step)
        if self.first_order and state.updates > 0:
            state.later_steps.append(step)
        return output

    def observe(self, state: InnerLoopState, output: ModelOutput, alive: Tensor) -> None:
        """Record the step's row ``[h_t || π_t]``; after k rows take the inner step for the episodes
        still running (``alive``), up to the rollout's update limit."""
        rows = self._chunk_rows(state, output)
        if rows is not None and state.updates < self.max_updates and bool(alive.any()):
            self.adapt(state, rows, alive)

    def compact(self, state: InnerLoopState, keep: Tensor) -> None:
        """Keep only the rows ``keep`` (increasing indices into the current batch) of ``state``, at
        any step. Dropped episodes must never adapt again and must not contribute to the outer loss
        after this point. Recorded steps and rows keep their tensors (their ``ids`` say which
        episodes their rows are); the next inner step differentiates with respect to the chunk's
        :attr:`InnerLoopState.sources`, so the gradient of every row of the chunk, before and after
        this call, reaches the episode's fast weights."""
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

    def replay(
        self, obs: dict[str, Tensor], prev_policy: Tensor, acted: Tensor
    ) -> tuple[Tensor, Tensor, InnerLoopState]:
        """``(logits [T', B, A], values [T', B], state)``: a segment of ``B`` whole episodes replayed
        through the inner loop from the current parameters, the adaptive counterpart of
        :meth:`~mapless.models.base.RecurrentNavModel.replay` (PPO's update).

        ``obs [T, B, ...]`` and ``prev_policy [T, B, 6]`` as recorded while acting; ``acted [T, B]``
        (bool): the steps each episode took, from its first step on (every episode starts at row 0,
        from the zero state). ``T'`` is the longest episode. Only the episodes still running are
        stepped: an episode that ended leaves the batch (:meth:`compact`), and its later outputs are
        zeros for the loss to mask out. :meth:`backward` with ``state`` carries a loss of the outputs
        into ``.grad``.

        Between two inner steps the fast weights are fixed and the previous policies are recorded,
        so unless the encoder reads the recurrent state (or draws dropout masks, whose order would
        change: training mode) a chunk's steps are encoded together and multiplied by ``weight_ih``
        in one product (:class:`_EncodedChunk`); a step then reads only ``weight_hh``, where the
        per-step product read the whole LSTM weight (the replay's largest cost in profiles). The
        values and gradients are the per-step ones up to the summation order (tests/test_meta.py)."""
        steps, batch = int(acted.sum(0).max()), acted.shape[1]
        device = prev_policy.device
        state = self.start(batch)
        # in the parameters' dtype: spatt's encoder multiplies h by its weights
        dtype = state.lstm.cell.weight_hh.dtype
        hidden = tuple(h.to(dtype) for h in self.model.initial_state(batch, device))
        rows = torch.arange(batch, device=device)  # the running episodes' columns (= state.ids)
        ahead = not (self.model.encoder_reads_state or self.model.training)
        lengths = acted.sum(0)
        chunk: _EncodedChunk | None = None
        logits, values = [], []
        for t in range(steps):
            if ahead:
                if chunk is None or not chunk.covers(t, state.updates):
                    chunk = self._encode_chunk(state, obs, prev_policy, lengths, t, steps)
                x, input_gates, critic_input = chunk.step(t)
                fast_step = self.model.fast_step_encoded(
                    state.fast, x, input_gates, critic_input, hidden, state.lstm, state.low_rank
                )
                out = self._record(state, fast_step)
            else:
                step_obs = {key: value[t].index_select(0, rows) for key, value in obs.items()}
                out = self.forward(state, step_obs, hidden, prev_policy[t].index_select(0, rows))
            alive = acted[t + 1].index_select(0, rows) if t + 1 < len(acted) else acted.new_zeros(len(rows))
            self.observe(state, out, alive)
            logits.append(out.logits.new_zeros(batch, out.logits.shape[-1]).index_copy(0, rows, out.logits))
            values.append(out.value.new_zeros(batch).index_copy(0, rows, out.value.reshape(-1)))
            hidden = out.hidden
            if t + 1 < steps and not bool(alive.all()):
                keep = alive.nonzero().squeeze(1)
                self.compact(state, keep)
                rows = rows.index_select(0, keep)
                hidden = tuple(h.index_select(0, keep) for h in hidden)
        return torch.stack(logits), torch.stack(values), state

    def _encode_chunk(
        self,
        state: InnerLoopState,
        obs: dict[str, Tensor],
        prev_policy: Tensor,
        lengths: Tensor,
        start: int,
        steps: int,
    ) -> _EncodedChunk:
        """The encodings of the replay's steps from ``start`` up to the next inner step (the last
        step when no more come) of the episodes running at ``start`` (``state.ids``, whose fast
        weights are ``state.fast``), with their ``weight_ih`` products."""
        k = self.steps
        end = min(steps, (start // k + 1) * k) if state.updates < self.max_updates else steps
        span, ids = end - start, state.ids
        left = (lengths.index_select(0, ids) - start).clamp(max=span)  # steps in the chunk, >= 1
        offsets = torch.arange(span, device=ids.device)
        # An episode that ends inside the chunk repeats its last step to fill its row of the
        # [B, L] grid: encoded (real data, finite gradients) but never read.
        times = start + torch.minimum(offsets.unsqueeze(0), (left - 1).unsqueeze(1))  # [B, L]
        columns = ids.unsqueeze(1).expand_as(times)
        x, critic_input = self.model.encoded_steps(
            state.fast,
            {key: value[times, columns] for key, value in obs.items()},
            prev_policy[times, columns],
            state.lstm,
        )
        # Step start + j runs the episodes with more than j steps left, in ids' order: time-major
        # rows of the episode-major grid, one slice per step.
        running = offsets.unsqueeze(1) < left.unsqueeze(0)  # [L, B]
        step, episode = running.nonzero().unbind(1)
        order = episode * span + step
        counts = running.sum(1).tolist()
        x = x.flatten(0, 1).index_select(0, order)
        # split, not one slice per step: its backward stacks the steps' gradients in one copy
        critic = (
            [None] * span
            if critic_input is None
            else critic_input.flatten(0, 1).index_select(0, order).split(counts)
        )
        return _EncodedChunk(
            start, state.updates, x.split(counts), state.lstm.input_gates(x).split(counts), critic
        )

    # -- inner step ----------------------------------------------------------------------------
    def adapt(self, state: InnerLoopState, rows: Tensor, active: Tensor) -> None:
        """One inner SGD step of the episodes where ``active`` (``[B]`` bool) on ``rows [B, k, H+6]``."""
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
                g = align(g, ids, state.ids)
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

    def _append_low_rank(
        self, state: InnerLoopState, steps: list[Step], grads: tuple[Tensor | None, ...]
    ) -> None:
        """Add this inner step's factors of the LSTM matrices' update (``δ`` and ``[x || h]``)."""
        deltas, inputs = [], []
        for step, g in zip(steps, grads, strict=True):
            g = torch.zeros_like(step.gates) if g is None else g
            deltas.append(align(g, step.ids, state.ids))
            inputs.append(align(step.inputs, step.ids, state.ids))
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
        """New factors for the steps to come (their gradients are summed once, mapless.agent.fast_weights)."""
        state.low_rank = LowRankUpdates(left, right)
        state.left, state.right = state.low_rank.left, state.low_rank.right

    # -- meta-gradient -------------------------------------------------------------------------
    def backward(self, state: InnerLoopState, loss: Tensor) -> None:
        """Accumulate the meta-gradient of the outer ``loss`` (a scalar) into ``.grad`` of θ_0 and φ."""
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


@dataclass
class _EncodedChunk:
    """A chunk of replayed steps encoded at once (:meth:`InnerLoop._encode_chunk`): per step, the
    running episodes' LSTM inputs x, their products with ``weight_ih`` and the critic's extra input."""

    start: int
    updates: int  # the inner steps taken before it: its fast weights
    x: tuple[Tensor, ...]
    input_gates: tuple[Tensor, ...]
    critic_input: tuple[Tensor, ...] | list[None]

    def covers(self, t: int, updates: int) -> bool:
        return updates == self.updates and self.start <= t < self.start + len(self.x)

    def step(self, t: int) -> tuple[Tensor, Tensor, Tensor | None]:
        j = t - self.start
        return self.x[j], self.input_gates[j], self.critic_input[j]


def _low_rank_inner_product(
    state: InnerLoopState, later: list[Step], outer: tuple[Tensor | None, ...]
) -> Tensor:
    """``Σ_i <g_i, v_i>`` of the LSTM matrices in factored form: ``g_i = Σ_s δ_s r_sᵀ`` and
    ``v_i = Σ_{t acted with θ_{i+1} or later} Δ_t r_tᵀ``, so ``<g_i, v_i> = Σ_{s,t} (δ_s·Δ_t)(r_s·r_t)``
    per episode (rows of different batch sizes are matched through their episode ids)."""
    total = later[0].gates.new_zeros(())
    size = state.batch_size
    outer_d = torch.stack(
        [
            scatter_rows(torch.zeros_like(s.gates) if d is None else d, s.ids, size)
            for s, d in zip(later, outer, strict=True)
        ],
        dim=1,
    ).detach()
    outer_r = torch.stack([scatter_rows(s.inputs.detach(), s.ids, size) for s in later], dim=1)
    acted = [s.updates for s in later]  # nondecreasing: the steps are in time order
    for i, (delta, right, ids) in enumerate(state.factor_records):
        # the steps that used θ_{i+1} or a later θ (θ_{j+1} = θ_j - α g_j.detach()): a suffix, a view
        first = bisect.bisect_right(acted, i)
        if first == len(acted):
            continue
        deltas = torch.einsum("bso,bto->bst", scatter_rows(delta, ids, size), outer_d[:, first:])
        inputs = torch.einsum("bsd,btd->bst", scatter_rows(right, ids, size), outer_r[:, first:])
        total = total + (deltas * inputs).sum()
    return total


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
