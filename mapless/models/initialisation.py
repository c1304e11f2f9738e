"""SAVN's weight initialisation, which every model following SAVN's layout uses."""

from __future__ import annotations

import math

import torch
from torch import nn


def glorot_init(module: nn.Module) -> None:
    """SAVN's ``weights_init``: uniform(±sqrt(6 / (fan_in + fan_out))) for every Conv/Linear weight,
    fan counts including the kernel, biases 0. Applied before the learned-loss modules exist, which
    (as in SAVN) keep PyTorch's default init."""
    for m in module.modules():
        if isinstance(m, nn.Conv1d | nn.Conv2d | nn.Linear):
            receptive = math.prod(m.weight.shape[2:]) if m.weight.dim() > 2 else 1
            fan_in, fan_out = m.weight.shape[1] * receptive, m.weight.shape[0] * receptive
            bound = math.sqrt(6.0 / (fan_in + fan_out))
            with torch.no_grad():
                m.weight.uniform_(-bound, bound)
                if m.bias is not None:
                    m.bias.zero_()


def normalized_column_init(linear: nn.Linear, std: float) -> None:
    """Rows of Gaussian weights rescaled to norm ``std`` (SAVN's actor 0.01 / critic 1.0), bias 0."""
    with torch.no_grad():
        w = torch.randn_like(linear.weight)
        linear.weight.copy_(w * std / w.pow(2).sum(dim=1, keepdim=True).sqrt())
        if linear.bias is not None:
            linear.bias.zero_()


def init_heads_and_lstm(model: nn.Module) -> None:
    """The rest of SAVN's init: actor std 0.01, critic std 1.0, LSTM biases 0 (weights keep PyTorch's)."""
    normalized_column_init(model.actor_linear, 0.01)
    normalized_column_init(model.critic_linear, 1.0)
    with torch.no_grad():
        model.lstm.bias_ih.zero_()
        model.lstm.bias_hh.zero_()
