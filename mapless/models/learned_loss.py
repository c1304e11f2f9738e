"""SAVN's learned interaction loss L_int^φ: a two-block temporal convolution over the last k rows
``[h_t || π_t]``. As in SAVN the k time steps are the Conv1d *input channels* and the H+6 features are
the sequence axis; block 0 maps k -> 10 channels (kernel 2, dilation 1), block 1 maps 10 -> 1
(kernel 2, dilation 2), each causally chomped and followed by LeakyReLU(0.01). The loss is the L2
norm of the resulting (H+6)-vector. The parameter names start with ``ll_`` as in SAVN (so checkpoints
keep its keys); what keeps them out of the inner step is their role, :data:`LEARNED_LOSS_ROLES`."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.models.roles import ParameterRoles

#: The roles of what :class:`LearnedLossMixin` builds: φ, never adapted by the inner step.
LEARNED_LOSS_ROLES = ParameterRoles(learned_loss=("ll_tc", "ll_key", "ll_linear"))


class TemporalBlock(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, dilation: int, with_dead_conv: bool):
        super().__init__()
        self.dilation = dilation
        self.ll_conv1 = nn.Conv1d(
            in_channels, out_channels, kernel_size=2, dilation=dilation, padding=dilation
        )
        if with_dead_conv:
            # SAVN defines a second conv per block but never applies it; kept only for key/count parity.
            self.ll_conv2 = nn.Conv1d(
                out_channels, out_channels, kernel_size=2, dilation=dilation, padding=dilation
            )

    def forward(self, x: Tensor) -> Tensor:
        y = self.ll_conv1(x)[..., : -self.dilation]  # chomp: keep the output causal and length-preserving
        return F.leaky_relu(y, 0.01)


class TemporalInteractionLoss(nn.Module):
    def __init__(self, steps: int = 6, reference_extras: bool = False):
        super().__init__()
        self.steps = steps
        self.ll_temporal_block0 = TemporalBlock(steps, 10, 1, reference_extras)
        self.ll_temporal_block1 = TemporalBlock(10, 1, 2, reference_extras)

    def forward(self, rows: Tensor) -> Tensor:
        """``rows [B, k, D]`` -> ``[B]``."""
        if rows.shape[-2] != self.steps:
            raise ValueError(f"the learned loss needs exactly {self.steps} rows, got {rows.shape[-2]}")
        out = self.ll_temporal_block1(self.ll_temporal_block0(rows))
        # sqrt(Σx² + ε²) rather than .norm(): identical values, but no NaN gradient at 0.
        return torch.sqrt(out.flatten(1).pow(2).sum(dim=-1) + 1e-24)


class LearnedLossMixin:
    """Adds ``ll_tc`` (and SAVN's dead ``ll_key``/``ll_linear`` with ``reference_extras``)."""

    def _build_learned_loss(self, with_key_linear: bool) -> None:
        cfg = self.config
        self.ll_tc = TemporalInteractionLoss(cfg.interaction_steps, cfg.reference_extras)
        if cfg.reference_extras and with_key_linear:
            width = cfg.hidden_size + 6
            self.ll_key = nn.Linear(width, width)
            self.ll_linear = nn.Linear(width, width)

    def learned_loss(self, rows: Tensor) -> Tensor:
        return self.ll_tc(rows)
