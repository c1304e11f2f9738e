"""Damaged copies of files, for the tests of readers that must refuse them cleanly."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np


def one_byte_flips(path: Path, count: int, seed: int = 0, mask: int = 0xFF) -> Iterator[int]:
    """Write ``count`` versions of ``path``, each with one byte (a fixed-seed random offset) XORed
    with ``mask``, yielding the offset after writing each; the original is put back at the end."""
    good = path.read_bytes()
    try:
        for offset in np.random.default_rng(seed).integers(0, len(good), count):
            damaged = bytearray(good)
            damaged[offset] ^= mask
            path.write_bytes(bytes(damaged))
            yield int(offset)
    finally:
        path.write_bytes(good)
