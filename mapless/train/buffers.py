"""Large tensors kept from one update to the next instead of allocated afresh.

A training update of the LSTM models makes a few tensors as large as the LSTM's weight matrices
(4H x (D + H), 30 MB in float32): the compute-dtype copy of the weights, their gradient, Adam's
denominator. Freshly allocated, each of them comes from new pages of memory (glibc hands blocks this
large straight back to the system when they are freed), and every first touch of a page is a page
fault: in profiles these copies ran 4-8x slower than the same copy into memory already in use, and
cvmeta's update spent ~15 % of its time there. A :class:`BufferPool` owned by the long-lived
trainer objects hands out the same storage at every update.
"""

from __future__ import annotations

import torch
from torch import Tensor


class BufferPool:
    """Named scratch tensors, allocated on first request and reused while shape, dtype and device
    stay the same. A buffer's content is whatever its last user wrote: callers overwrite it."""

    def __init__(self) -> None:
        self._buffers: dict[str, Tensor] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
        buffer = self._buffers.get(name)
        if buffer is None or buffer.shape != shape or buffer.dtype != dtype or buffer.device != device:
            buffer = self._buffers[name] = torch.empty(shape, dtype=dtype, device=device)
        return buffer

    def __len__(self) -> int:
        return len(self._buffers)
