"""Atomic file writes: a reader (or a run killed mid-write) sees a file's old content or its new
content, never a torn mixture.

Everything mapless writes for later reuse goes through :func:`replacing`: checkpoints, the scene
cache, episode sets, offline data, evaluation caches and reports. A half-written evaluation cache
or episode file would otherwise break every later run that reads it.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """A temporary path next to ``path`` for the block to write; when the block ends normally it is
    flushed to disk and renamed over ``path`` (an atomic step on one filesystem), when it raises it
    is removed and ``path`` is left as it was. Parent folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    """``Path(path).write_bytes(data)``, atomically (:func:`replacing`)."""
    with replacing(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    """``Path(path).write_text(text)``, atomically (:func:`replacing`)."""
    with replacing(path) as tmp:
        tmp.write_text(text)
