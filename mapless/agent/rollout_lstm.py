"""The LSTM cell of one training rollout, with the gradient of its two weight matrices computed once.

Autograd differentiates ``gates_t = [x_t || h_{t-1}] W`` separately at every step t of a rollout:
one full-size gradient of W (4H x (D + H), 8M entries for SAVN's 3136-input LSTM) per step, summed
as it goes. Those memory-bound products and sums were over half of a batched meta-training update
in profiles. The gradient is ``Σ_t [x_t || h_{t-1}]ᵀ Δ_t`` with ``Δ_t = ∂L/∂gates_t``, i.e. one
matrix product of the stacked step inputs and gate gradients, so :class:`RolloutLstm`

* multiplies by W with a matmul whose backward passes gradient to the inputs only,
* records every step's input row ``[x_t || h_{t-1}]`` and product, and
* in :meth:`RolloutLstm.grad` asks autograd for the products' gradients ``Δ_t`` alongside the other
  parameters' and adds ``Δᵀ [x || h]`` to the gradients of ``weight_ih`` and ``weight_hh``.

A product may also take one of the two matrices alone (:meth:`RolloutLstm.input_gates`,
:meth:`RolloutLstm.hidden_gates`): the inner loop's replay multiplies a whole chunk's inputs by
``weight_ih`` at once and only ``h`` by ``weight_hh`` step by step; each record then adds to its
matrix's gradient only.

Second-order meta-gradients stay exact: an inner step taken with ``create_graph=True`` multiplies by
W again in its backward (``g Wᵀ``); that product is recorded the same way, and its share of W's
gradient joins the same single product. The values and gradients are those of ``nn.LSTMCell`` up to
the floating-point summation order (tests/test_meta.py compares them with hand-unrolled autograd).
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor, nn

from mapless.agent.buffers import BufferPool


class _DeferredWeightMatmul(torch.autograd.Function):
    """``rows @ W`` (``rows @ W.T`` when ``transpose``) with W the recorder's operand, whose backward
    returns the rows' gradient only; W's is added up later from the recorder's records (see
    :class:`RolloutLstm`). The cell's two matrices are inputs only so that every product is a graph
    node, even of constant rows; no gradient flows to them through here."""

    @staticmethod
    def forward(
        ctx,
        rows: Tensor,
        weight_ih: Tensor,
        weight_hh: Tensor,
        transpose: bool,
        recorder: RolloutLstm,
        part: str | None,
    ) -> Tensor:
        # A weak reference: the recorder holds this node's output, and a strong one would close a
        # cycle through the autograd graph that Python's garbage collector cannot see (a leak).
        ctx.transpose, ctx.recorder, ctx.part = transpose, weakref.ref(recorder), part
        return recorder.multiply(rows, transpose, part)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None, None, None, None]:
        recorder = ctx.recorder()
        if recorder is None:
            raise RuntimeError("backward through a RolloutLstm that no longer exists (keep it until grad())")
        # The rows' gradient is a product with the same weight. Under create_graph (an inner step
        # of second-order meta-learning) it is itself recorded, so the outer backward can defer the
        # weight gradient of this use too; otherwise nothing will differentiate it again.
        if torch.is_grad_enabled():
            return _deferred_matmul(grad, not ctx.transpose, recorder, ctx.part), None, None, None, None, None
        return recorder.multiply(grad, not ctx.transpose, ctx.part), None, None, None, None, None


def _deferred_matmul(rows: Tensor, transpose: bool, recorder: RolloutLstm, part: str | None = None) -> Tensor:
    cell = recorder.cell
    out = _DeferredWeightMatmul.apply(rows, cell.weight_ih, cell.weight_hh, transpose, recorder, part)
    recorder.records.append((rows.detach(), out, transpose, part))
    return out


class RolloutLstm:
    """``cell``'s matrices for one rollout (create one per batch of episodes)."""

    def __init__(
        self,
        cell: nn.LSTMCell,
        record: bool = True,
        dtype: torch.dtype | None = None,
        buffers: BufferPool | None = None,
    ):
        """``record=False`` (test-time adaptation, no outer gradient): plain products, nothing kept.

        ``dtype=torch.bfloat16``: every product with the weight, and the final weight gradient, takes
        bfloat16 operands (accumulated in float32 by the CPU's bf16 dot-product instructions, rounded
        to bfloat16, returned as float32): 3-5x faster matrix products on CPUs with AVX512-BF16 or
        AMX, at bfloat16's 8-bit mantissa. Everything else stays float32.

        ``buffers``: where the operand and the weight gradients live; a trainer passes the same
        pool to every rollout (:mod:`mapless.agent.buffers`). A gradient :meth:`grad` returns stays
        valid until the pool's next rollout computes its own."""
        self.cell = cell
        self.record = record
        self.dtype = dtype if dtype is not None else cell.weight_ih.dtype
        self.buffers = buffers if buffers is not None else BufferPool()
        # Every product reads the weight along the dimension it reduces (``rows @ Mᵀ``, M row-major):
        # for the few-row products of a rollout that is up to 2x faster than reading across it
        # (docs/guide/training.md, "The LSTM weight read along the reduced dimension"). So the forward
        # products (input space -> gate space) read a
        # gate-major copy [4H, D + H] and the transposed ones (an inner step's backward) an
        # input-major copy [D + H, 4H].
        self._gate_major = self._copy_of_weight("lstm.operand.gate_major", input_major=False)
        self._input_major = self._copy_of_weight("lstm.operand.input_major", input_major=True)
        #: every product with the weight: (its left factor, the product, transposed?, the matrix it
        #: took: "weight_ih", "weight_hh", or None for both)
        self.records: list[tuple[Tensor, Tensor, bool, str | None]] = []
        #: the weight gradients the last :meth:`grad` returned (pool buffers, see accumulate_grad)
        self.weight_gradients: tuple[Tensor, ...] = ()

    @property
    def device(self) -> torch.device:
        return self.cell.weight_ih.device

    def gates(self, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        """``([x || h], [x || h] · Wᵀ)``: the step's input row and its gate pre-activations before the
        biases (the caller adds biases and any per-episode terms; their sum has the same gradient)."""
        inputs = torch.cat([x, h], dim=-1)
        if not self.record:
            return inputs, self.multiply(inputs, transpose=False)
        return inputs, _deferred_matmul(inputs, False, self)

    def input_gates(self, x: Tensor) -> Tensor:
        """``x · weight_ihᵀ`` (recorded like :meth:`gates`): the input's share of the gate
        pre-activations, for any number of rows at once."""
        return self._part_product(x, "weight_ih")

    def hidden_gates(self, h: Tensor) -> Tensor:
        """``h · weight_hhᵀ`` (recorded like :meth:`gates`): the recurrent share, which reads only
        ``weight_hh``, a ``H / (D + H)`` part of the weights."""
        return self._part_product(h, "weight_hh")

    def _part_product(self, rows: Tensor, part: str) -> Tensor:
        if not self.record:
            return self.multiply(rows, False, part)
        return _deferred_matmul(rows, False, self, part)

    def multiply(self, rows: Tensor, transpose: bool, part: str | None = None) -> Tensor:
        """``rows · W`` (``rows · Wᵀ`` when ``transpose``) in the rollout's compute dtype, returned in
        ``rows``' dtype; no graph. ``part``: one of the two matrices alone (a view of the copy)."""
        columns = self._input_columns(part)
        weight = self._input_major[columns] if transpose else self._gate_major[:, columns]
        return _product(rows, weight.T, self.dtype)

    def _input_columns(self, part: str | None) -> slice:
        """The columns of ``[weight_ih || weight_hh]`` that ``part`` names (None: all)."""
        split = self.cell.input_size
        return {None: slice(None), "weight_ih": slice(None, split), "weight_hh": slice(split, None)}[part]

    def _copy_of_weight(self, name: str, input_major: bool) -> Tensor:
        """``[weight_ih || weight_hh]`` in the compute dtype, transposed when ``input_major``."""
        cell = self.cell
        inputs, hidden, gates = cell.input_size, cell.hidden_size, cell.weight_ih.shape[0]
        shape = (inputs + hidden, gates) if input_major else (gates, inputs + hidden)
        operand = self.buffers.get(name, shape, self.dtype, cell.weight_ih.device)
        with torch.no_grad():
            if input_major:  # both transposes written into one buffer: one copy, not a cat then a copy
                operand[:inputs].copy_(cell.weight_ih.T)
                operand[inputs:].copy_(cell.weight_hh.T)
            else:
                operand[:, :inputs].copy_(cell.weight_ih)
                operand[:, inputs:].copy_(cell.weight_hh)
        return operand

    def grad(
        self,
        loss: Tensor,
        inputs: list[Tensor],
        retain_graph: bool = False,
    ) -> tuple[Tensor | None, ...]:
        """``torch.autograd.grad(loss, inputs, allow_unused=True)`` with the deferred gradient of the
        cell's ``weight_ih`` / ``weight_hh`` added where they appear in ``inputs``.

        A product ``r W`` (r in the D + H input space) contributes ``(∂L/∂(rW))ᵀ r`` to W; a
        transposed one ``g Wᵀ`` (an inner step's backward, g in the 4H gate space) contributes
        ``gᵀ ∂L/∂(gWᵀ)``: both are (gate-space)ᵀ (input-space) pairs, summed in one product."""
        records = [r for r in self.records if r[1].requires_grad]  # none is not, unless W is frozen
        products = [r[1] for r in records]
        grads = torch.autograd.grad(loss, [*inputs, *products], retain_graph=retain_graph, allow_unused=True)
        grads, outer = list(grads[: len(inputs)]), grads[len(inputs) :]
        # per matrix, its (gate-space, input-space) row pairs: a record of both matrices adds to
        # each the columns of its input side that belong to it
        sides: dict[str, tuple[list[Tensor], list[Tensor]]] = {"weight_ih": ([], []), "weight_hh": ([], [])}
        for (rows, _, transpose, part), g in zip(records, outer, strict=True):
            if g is None:
                continue
            gate, input_side = (rows, g) if transpose else (g, rows)
            for name in (part,) if part is not None else tuple(sides):
                sides[name][0].append(gate)
                sides[name][1].append(
                    input_side if part is not None else input_side[:, self._input_columns(name)]
                )
        if not any(gate_side for gate_side, _ in sides.values()):
            return tuple(grads)
        # every record took both matrices (the per-step products): their gate rows are stacked once
        both = all(part is None for _, _, _, part in records)
        parts, gate_columns = [], None
        for name, (gate_side, input_side) in sides.items():
            parameter = getattr(self.cell, name)
            positions = [i for i, tensor in enumerate(inputs) if tensor is parameter]
            if not positions or not gate_side:
                continue
            if gate_columns is None or not both:
                gate_columns = self._columns(self._rows("gate_rows", gate_side))  # [4H, N]
            input_rows = self._rows(f"input_rows.{name}", input_side)  # [N, D] or [N, H]
            part = self._weight_gradient(name, gate_columns, input_rows)
            parts.append(part)
            for i in positions:
                grads[i] = part if grads[i] is None else grads[i] + part
        self.weight_gradients = tuple(parts)
        return tuple(grads)

    def _rows(self, name: str, pieces: list[Tensor]) -> Tensor:
        """``torch.cat(pieces)`` in the compute dtype, written into the pool."""
        rows = sum(piece.shape[0] for piece in pieces)
        out = self.buffers.rows(name, rows, tuple(pieces[0].shape[1:]), self.dtype, pieces[0].device)
        return torch.cat(pieces, out=out)

    def _columns(self, rows: Tensor) -> Tensor:
        """``rows.T``, the weight gradient's left operand; in bfloat16 a contiguous copy in the pool,
        because the product with a transposed view ran at half the speed (float32: within 15 %, less
        than the copy costs; docs/guide/training.md, "The LSTM weight read along the reduced dimension")."""
        if rows.dtype != torch.bfloat16:
            return rows.T
        count, width = rows.shape
        flat = self.buffers.rows("gate_columns", count * width, (), rows.dtype, rows.device)
        return flat.view(width, count).copy_(rows.T)

    def _weight_gradient(self, name: str, gate_columns: Tensor, input_rows: Tensor) -> Tensor:
        """``gate_columns · input_rows`` (compute-dtype operands) in the pool's buffer for ``name``'s
        gradient."""
        parameter = getattr(self.cell, name)
        shape, device = tuple(parameter.shape), parameter.device
        out = self.buffers.get(f"grad.{name}", shape, parameter.dtype, device)
        if parameter.grad is not None and parameter.grad.data_ptr() == out.data_ptr():
            out = torch.empty_like(out)  # still the .grad of an earlier backward: leave it intact
        with torch.no_grad():
            if self.dtype == parameter.dtype:
                return torch.mm(gate_columns, input_rows, out=out)
            low = self.buffers.get(f"grad.{name}.low", shape, self.dtype, device)
            return out.copy_(torch.mm(gate_columns, input_rows, out=low))


def _product(left: Tensor, right: Tensor, dtype: torch.dtype) -> Tensor:
    """``left @ right`` with operands in ``dtype``, the result in ``left``'s dtype."""
    if left.dtype == dtype and right.dtype == dtype:
        return left @ right
    return (left.to(dtype) @ right.to(dtype)).to(left.dtype)


def accumulate_grad(
    params: list[Tensor], grads: tuple[Tensor | None, ...], adopt: tuple[Tensor, ...] = ()
) -> None:
    """Add ``grads`` into ``.grad`` as ``Tensor.backward`` would (None: no gradient).

    A gradient in ``adopt`` (a buffer nothing else writes until the next rollout, such as
    :attr:`RolloutLstm.weight_gradients`) becomes a missing ``.grad`` as it is, without a copy."""
    for p, g in zip(params, grads, strict=True):
        if g is None:
            continue
        if p.grad is not None:
            p.grad = p.grad + g.detach()
        elif any(g is a for a in adopt):
            p.grad = g
        else:
            p.grad = g.detach().clone()
