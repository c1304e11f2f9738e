"""Re-evaluating a recurrent policy over a recorded segment (the PPO update's forward pass).

A segment holds, per environment slot, ``T`` consecutive steps that may span several episodes:
``starts[t, b]`` marks a step that opened a new episode, where the recurrent state restarts from
zeros. The previous step's policy, which every model reads, is replayed as it was recorded while
acting: under PPO it is part of the observation (the acting policy's own output), which makes the
encoder's input independent of the recurrent state.

So, for models whose encoder does not read the recurrent state (every non-adaptive model), the
encoder runs once over all ``T · B`` rows, and the LSTM's input product ``W_ih x`` for the whole
segment is one matrix product; only ``W_hh h`` is computed step by step. The values are those of
``T`` calls of the model's ``forward`` up to rounding (tests/test_ppo.py).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.profiler import record_function

from mapless.models.base import RecurrentNavModel
from mapless.models.layers import lstm_state_from_gates


def replay_segment(
    model: RecurrentNavModel,
    obs: dict[str, Tensor],
    prev_policy: Tensor,
    starts: Tensor,
    hidden: tuple[Tensor, Tensor],
) -> tuple[Tensor, Tensor]:
    """``(logits [T, B, A], values [T, B])`` of ``model`` over a segment.

    :param obs: observation tensors ``[T, B, ...]`` (docs/observations.md, with a time dimension).
    :param prev_policy: ``[T, B, 6]`` the previous policy each step was given while acting.
    :param starts: ``[T, B]`` bool, the step opened a new episode (recurrent state zeroed before it).
    :param hidden: ``(h, c)`` ``[B, H]`` before the segment's first step.
    """
    steps, batch = starts.shape
    flat = {key: value.flatten(0, 1) for key, value in obs.items()}
    flat_hidden = model.initial_state(steps * batch, prev_policy.device)  # unread by these encoders
    cell = model.lstm
    # The labels name the parts in profiles (bench/frame_cost.py); they cost nothing otherwise.
    with record_function("encoder"):
        x, critic_input = model.encode(model.describe(flat), flat_hidden, prev_policy.flatten(0, 1))
        input_gates = F.linear(x, cell.weight_ih, cell.bias_ih + cell.bias_hh).view(steps, batch, -1)
    keep = (~starts).to(x.dtype).unsqueeze(-1)
    h, c = hidden
    outputs = []
    with record_function("lstm"):
        for t in range(steps):
            h, c = h * keep[t], c * keep[t]
            h, c = lstm_state_from_gates(input_gates[t] + F.linear(h, cell.weight_hh), c)
            outputs.append(h)
    with record_function("heads"):
        h_all = torch.stack(outputs).flatten(0, 1)
        logits = model.actor_linear(h_all).view(steps, batch, -1)
        values = model.value(h_all, critic_input).view(steps, batch)
    return logits, values
