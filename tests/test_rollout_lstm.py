"""RolloutLstm: the LSTM weight gradient computed once per rollout equals plain autograd's, and a
finished rollout's graph is freed."""

from __future__ import annotations

import gc
import weakref

import torch
from torch import nn

from mapless.agent.rollout_lstm import RolloutLstm
from mapless.models.layers import lstm_state_from_gates, lstm_step


def _rollout(cell, xs, lstm=None):
    h = c = torch.zeros(xs.shape[1], cell.hidden_size, dtype=xs.dtype)
    loss = 0.0
    for x in xs:
        if lstm is None:
            h, c = lstm_step(x, (h, c), cell)
        else:
            _, product = lstm.gates(x, h)
            h, c = lstm_state_from_gates(product + cell.bias_ih + cell.bias_hh, c)
        loss = loss + (h * torch.linspace(-1, 1, h.shape[-1], dtype=h.dtype)).sum()
    return loss


def test_gradient_equals_plain_autograd_including_a_second_order_use():
    torch.manual_seed(0)
    cell = nn.LSTMCell(7, 5).double()
    xs = torch.randn(4, 3, 7, dtype=torch.float64)
    params = list(cell.parameters())
    # Constant inputs first: the first step's rows need no gradient, its product still feeds W's.
    expected = torch.autograd.grad(_rollout(cell, xs), params)
    lstm = RolloutLstm(cell)
    got = lstm.grad(_rollout(cell, xs, lstm), params)
    for g, e in zip(got, expected, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-10, atol=1e-12)

    xs.requires_grad_()
    params = [*cell.parameters(), xs]

    expected = torch.autograd.grad(_rollout(cell, xs), params)
    lstm = RolloutLstm(cell)
    got = lstm.grad(_rollout(cell, xs, lstm), params)
    for g, e in zip(got, expected, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-10, atol=1e-12)

    # Second order: the loss uses the gradient of an inner loss (an inner step's backward products
    # with W are themselves recorded and deferred).
    def outer(lstm):
        inner = _rollout(cell, xs, lstm)
        (gx,) = torch.autograd.grad(inner, xs, create_graph=True)
        return gx.pow(2).sum()

    expected = torch.autograd.grad(outer(None), params)
    lstm = RolloutLstm(cell)
    got = lstm.grad(outer(lstm), params)
    for g, e in zip(got, expected, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-9, atol=1e-12)


def test_a_finished_rollout_is_freed():
    cell = nn.LSTMCell(7, 5)
    lstm = RolloutLstm(cell)
    loss = _rollout(cell, torch.randn(3, 2, 7), lstm)
    product = weakref.ref(lstm.records[0][1])
    lstm.grad(loss, list(cell.parameters()))
    del lstm, loss
    gc.collect()
    assert product() is None  # no reference cycle through the autograd graph keeps it alive


def test_bfloat16_products_stay_close_to_float32_including_second_order():
    torch.manual_seed(0)
    cell = nn.LSTMCell(48, 32)
    xs = torch.randn(6, 4, 48, requires_grad=True)
    params = [*cell.parameters(), xs]

    def outer(lstm):
        inner = _rollout(cell, xs, lstm)
        (gx,) = torch.autograd.grad(inner, xs, create_graph=True)
        return inner + gx.pow(2).sum()

    exact = RolloutLstm(cell)
    expected = exact.grad(outer(exact), params)
    low = RolloutLstm(cell, dtype=torch.bfloat16)
    loss = outer(low)
    assert loss.dtype == torch.float32 and low.records[0][1].dtype == torch.float32
    got = low.grad(loss, params)
    for g, e in zip(got, expected, strict=True):
        assert g.dtype == torch.float32
        cosine = torch.nn.functional.cosine_similarity(g.flatten(), e.flatten(), dim=0)
        assert cosine > 0.999  # bfloat16's 8-bit mantissa: close, but not equal ...
    assert not all(torch.equal(g, e) for g, e in zip(got, expected, strict=True))  # ... products did change
