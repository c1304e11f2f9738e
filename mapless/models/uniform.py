"""``random``: the uniform policy over the 6 actions (SAVN's ``RandomNavigationAgent``); no parameters."""

from __future__ import annotations

import torch
from torch import Tensor

from mapless.models.base import NUM_ACTIONS, ModelOutput, NavModel


class RandomModel(NavModel):
    description = "uniform over the 6 actions (no parameters, nothing to train)"

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        batch = prev_policy.shape[0]
        # Equal logits give the uniform distribution; the state passes through unchanged.
        logits = torch.zeros(batch, NUM_ACTIONS, dtype=prev_policy.dtype, device=prev_policy.device)
        return ModelOutput(logits, logits.new_zeros(batch, 1), hidden)
