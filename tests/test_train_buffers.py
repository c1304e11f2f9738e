"""Buffers reused across updates (mapless.agent.buffers): the LSTM operand and weight gradients of
consecutive rollouts, Adam's denominator. Reuse must never change a result."""

from __future__ import annotations

import math

import torch
from torch import nn

from mapless.agent.buffers import BufferPool
from mapless.agent.rollout_lstm import RolloutLstm, accumulate_grad
from mapless.models.layers import lstm_state_from_gates
from mapless.train.optim import SharedAdam


def test_pool_reuses_storage_and_replaces_on_a_new_shape():
    pool = BufferPool()
    a = pool.get("x", (3, 4), torch.float32, torch.device("cpu"))
    assert pool.get("x", (3, 4), torch.float32, torch.device("cpu")) is a
    assert pool.get("x", (4, 3), torch.float32, torch.device("cpu")).shape == (4, 3)
    assert pool.get("x", (4, 3), torch.float64, torch.device("cpu")).dtype == torch.float64
    assert len(pool) == 1


def _loss(cell: nn.LSTMCell, lstm: RolloutLstm | None, xs: torch.Tensor) -> torch.Tensor:
    h = c = torch.zeros(xs.shape[1], cell.hidden_size, dtype=xs.dtype)
    for x in xs:
        if lstm is None:
            gates = x @ cell.weight_ih.T + h @ cell.weight_hh.T
        else:
            _, gates = lstm.gates(x, h)
        h, c = lstm_state_from_gates(gates + cell.bias_ih + cell.bias_hh, c)
    return h.pow(2).sum()


def test_rollouts_sharing_a_pool_give_each_their_own_exact_gradients():
    torch.manual_seed(0)
    cell = nn.LSTMCell(5, 3).double()
    params = list(cell.parameters())
    pool = BufferPool()
    for step in range(3):  # weights change between rollouts, as after an optimizer step
        xs = torch.randn(4, 2, 5, dtype=torch.float64)
        expected = torch.autograd.grad(_loss(cell, None, xs), params)
        for p in params:  # the trainer's zero_grad(set_to_none=True), before the rollout
            p.grad = None
        lstm = RolloutLstm(cell, buffers=pool)
        grads = lstm.grad(_loss(cell, lstm, xs), params)
        accumulate_grad(params, grads, adopt=lstm.weight_gradients)
        for p, e in zip(params, expected, strict=True):
            torch.testing.assert_close(p.grad, e, rtol=1e-12, atol=1e-12)
        if step == 0:
            first_buffer = cell.weight_ih.grad
        else:
            assert cell.weight_ih.grad.data_ptr() == first_buffer.data_ptr()  # no new allocation
        with torch.no_grad():
            for p in params:
                p.add_(0.1 * torch.randn_like(p))


def test_a_second_backward_without_zeroing_adds_to_the_gradient_it_would_overwrite():
    torch.manual_seed(1)
    cell = nn.LSTMCell(5, 3).double()
    params = list(cell.parameters())
    pool = BufferPool()
    batches = [torch.randn(3, 2, 5, dtype=torch.float64) for _ in range(2)]
    expected = torch.autograd.grad(sum(_loss(cell, None, xs) for xs in batches), params)
    for xs in batches:  # two rollouts accumulate into .grad before any optimizer step
        lstm = RolloutLstm(cell, buffers=pool)
        accumulate_grad(params, lstm.grad(_loss(cell, lstm, xs), params), adopt=lstm.weight_gradients)
    for p, e in zip(params, expected, strict=True):
        torch.testing.assert_close(p.grad, e, rtol=1e-12, atol=1e-12)


def test_shared_adam_follows_the_references_rule_step_after_step():
    torch.manual_seed(2)
    lr, (b1, b2), eps = 1e-2, (0.9, 0.999), 1e-3
    p = nn.Parameter(torch.randn(6, 4, dtype=torch.float64))
    optimizer = SharedAdam([p], lr=lr, betas=(b1, b2), eps=eps, amsgrad=True)
    value, m, v, v_max = p.detach().clone(), torch.zeros_like(p), torch.zeros_like(p), torch.zeros_like(p)
    for t in range(1, 4):
        g = torch.randn_like(p) * (4 - t)  # shrinking gradients: amsgrad's max matters
        p.grad = g.clone()
        optimizer.step()
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        v_max = torch.maximum(v_max, v)
        value = value - lr * math.sqrt(1 - b2**t) / (1 - b1**t) * m / (v_max.sqrt() + eps)
        torch.testing.assert_close(p.detach(), value, rtol=1e-12, atol=1e-12)
