"""Training precision (``TrainConfig.precision``): ``fp32`` or ``bf16``.

``bf16`` changes the two places of a training rollout where the arithmetic is:

* the LSTM's weight products (:class:`~mapless.train.rollout_lstm.RolloutLstm` with
  ``dtype=torch.bfloat16``): the forward products, the inner steps' backward products, the weight
  gradient;
* the observation encoders (GCNs, 1x1 convolutions, embeddings) run under ``torch.autocast`` to
  bfloat16, and their output returns to float32 (:func:`like` the LSTM state) before the LSTM.

Parameters, optimizer state, LSTM gates, heads, the learned loss and the A3C loss stay float32, and
evaluation runs in float32 unless asked otherwise (``mapless eval --bf16``).
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch

#: precision -> reduced compute dtype (None: the parameters' own, float32 in training).
PRECISIONS: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}


def encoder_autocast(dtype: torch.dtype | None, device: torch.device) -> AbstractContextManager:
    """Autocast to ``dtype`` on ``device``'s type (a no-op context for None)."""
    return torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def like(x: torch.Tensor | None, reference: torch.Tensor) -> torch.Tensor | None:
    """``x`` (an autocast output) back in the dtype of the rollout's state ``reference``."""
    return x if x is None or x.dtype == reference.dtype else x.to(reference.dtype)
