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

    def rows(
        self, name: str, rows: int, row_shape: tuple[int, ...], dtype: torch.dtype, device: torch.device
    ) -> Tensor:
        """The first ``rows`` rows of a buffer whose row count only grows (by a quarter at least, so
        that a slowly varying count does not reallocate at every update)."""
        buffer = self._buffers.get(name)
        fits = (
            buffer is not None
            and buffer.shape[0] >= rows
            and buffer.shape[1:] == row_shape
            and buffer.dtype == dtype
            and buffer.device == device
        )
        if not fits:
            capacity = max(rows, int(1.25 * buffer.shape[0]) if buffer is not None else 0)
            buffer = self._buffers[name] = torch.empty((capacity, *row_shape), dtype=dtype, device=device)
        return buffer[:rows]

    def __len__(self) -> int:
        return len(self._buffers)
