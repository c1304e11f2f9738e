"""Dropout whose mask costs a quarter of a random number per element.

``nn.Dropout`` on the CPU draws one Mersenne-Twister number per element (``bernoulli_``): for the
``[B, 64, 101]`` context descriptors of a B = 512 cvmeta rollout that is ~30 ms per step on one
core, 4 % of a training update. The mask needs far fewer random bits: :class:`Dropout` keeps an
element when 16 random bits exceed a threshold, and draws them as 64-bit words, four elements per
draw (3.7x faster at the models' shapes; docs/guide/training.md, "Dropout masks"). It works under
``vmap`` with ``randomness="different"`` (the inner loop's per-episode encoders), and uses the
default generator, so ``torch.manual_seed`` and the trainer's saved RNG state reproduce it.

The drop probability is ``p`` rounded to a multiple of 2⁻¹⁶ (exact for SAVN's 0.25); kept elements
are scaled by ``1 / (1 - p)`` of that rounded ``p``, so the expectation is unchanged. Off the CPU
(``F.dropout`` has fused kernels there) and in eval mode it is ``nn.Dropout``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

_LEVELS = 1 << 16  # resolution of the keep test: 16 random bits per element
_SHORTS_PER_WORD = 4


def keep_mask(shape: torch.Size, p: float, device: torch.device) -> Tensor:
    """Bool ``shape`` tensor, each element True with probability ``1 - round(p · 2¹⁶) / 2¹⁶``."""
    count = shape.numel()
    words = torch.randint(
        -(1 << 63),
        (1 << 63) - 1,
        ((count + _SHORTS_PER_WORD - 1) // _SHORTS_PER_WORD,),
        dtype=torch.int64,
        device=device,
    )
    shorts = words.view(torch.int16)[:count].view(shape)  # uniform over [-2¹⁵, 2¹⁵)
    return shorts >= round(p * _LEVELS) - _LEVELS // 2


class Dropout(nn.Module):
    """Drop-in for ``nn.Dropout(p)`` (no parameters or buffers: checkpoints are unchanged)."""

    def __init__(self, p: float = 0.5):
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"dropout probability must be in [0, 1), got {p}")
        self.p = p
        self._scale = 1.0 / (1.0 - round(p * _LEVELS) / _LEVELS)

    def forward(self, x: Tensor) -> Tensor:
        if not self.training or self.p == 0.0:
            return x
        if x.device.type != "cpu":
            return F.dropout(x, self.p, training=True)
        keep = keep_mask(x.shape, self.p, x.device)
        return x * keep.to(x.dtype).mul_(self._scale)

    def extra_repr(self) -> str:
        return f"p={self.p}"
