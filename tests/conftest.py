"""Test session setup: every test that builds scenes shares one throw-away cache folder, so a
scene is ray-cast at most once per session and the user's own cache is never touched."""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest
import torch

_SESSION_CACHE: str | None = None


def pytest_configure(config) -> None:
    global _SESSION_CACHE
    if "MAPLESS_TEST_KEEP_CACHE" not in os.environ:
        _SESSION_CACHE = tempfile.mkdtemp(prefix="mapless-test-cache-")
        os.environ["MAPLESS_CACHE"] = _SESSION_CACHE


def pytest_unconfigure(config) -> None:
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)


@pytest.fixture(scope="module")
def single_torch_thread():
    """Single-threaded torch, as in the spawn workers: two threads on a busy 2-core machine crawl."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
