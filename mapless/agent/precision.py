"""Training precision (``a3c.precision``, :class:`~mapless.train.config.A3CConfig`): ``fp32`` or ``bf16``.

``bf16`` changes the two places of a training rollout where the arithmetic is:

* the LSTM's weight products (:class:`~mapless.agent.rollout_lstm.RolloutLstm` with
  ``dtype=torch.bfloat16``): the forward products, the inner steps' backward products, the weight
  gradient;
* the observation encoders (GCNs, 1x1 convolutions, embeddings) run under ``torch.autocast`` to
  bfloat16, and their output returns to float32 (:func:`like` the LSTM state) before the LSTM.

Parameters, optimizer state, LSTM gates, heads, the learned loss and the A3C loss stay float32.
Evaluation runs in float32 unless asked otherwise; ``mapless eval --bf16`` means the same as here
(a model's step at a precision: :meth:`mapless.models.base.RecurrentNavModel.rollout_step`, which
applies both).

On the CPU, bfloat16 matrix products run through oneDNN, which compiles a kernel for every operand
shape it meets (4-5 ms each on a Sapphire Rapids core, against 0.4 ms for the product itself at
cvmeta's GCN shapes) and keeps the last 1,024 of them. A training rollout's products vary in their
row counts (running episodes, new in-view rows, frames per update), and a cvmeta run meets more
than 1,024 shapes within 30 updates, so with the default cache it keeps recompiling:
:func:`keep_compiled_kernels` enlarges that cache.
"""

from __future__ import annotations

import os

import torch

#: precision -> reduced compute dtype (None: the parameters' own, float32 in training).
PRECISIONS: dict[str, torch.dtype | None] = {"fp32": None, "bf16": torch.bfloat16}


#: oneDNN kernels kept compiled per process (oneDNN's default is 1,024).
KERNEL_CACHE_CAPACITY = 16384


def keep_compiled_kernels() -> None:
    """Enlarge oneDNN's kernel cache to :data:`KERNEL_CACHE_CAPACITY` unless the user set
    ``ONEDNN_PRIMITIVE_CACHE_CAPACITY``.

    oneDNN reads the variable when it creates its first kernel, so this must run before the first
    bfloat16 product of the process (trainers call it from ``configure_torch``). A cvmeta bf16
    update after 40 warm-up updates: 800 -> 685 ms, for 43 MB more memory (2026-12-03)."""
    os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", str(KERNEL_CACHE_CAPACITY))
