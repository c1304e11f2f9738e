"""Atomic file writes: a reader (or a run killed mid-write) sees a file's old content or its new
content, never a torn mixture.

Everything mapless writes for later reuse goes through :func:`replacing`: checkpoints, the scene
cache, episode sets, offline data, evaluation caches and reports. A half-written evaluation cache
or episode file would otherwise break every later run that reads it.
"""

from __future__ import annotations

import os
import secrets
import tempfile
from collections.abc import Iterable, Iterator
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


def unwritable(folder: str | Path, names: Iterable[str] = ()) -> str | None:
    """Why the files ``names`` (or, without names, any file) could not be written in ``folder``, its
    missing parents made on the way; None when they can. Commands check their output before the
    work whose results it holds, so that an unwritable path costs no work. Nothing is created: the
    nearest folder that exists is probed with a temporary file."""
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a folder"
    taken = [folder / name for name in names if (folder / name).is_dir()]
    if taken:
        return f"{taken[0]} is a folder"
    try:
        with tempfile.TemporaryFile(dir=existing, prefix=".probe-"):
            pass
    except OSError as error:
        return f"cannot write in {existing}: {error.strerror or error}"
    return None
