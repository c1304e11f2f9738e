"""Test session setup: every test that builds scenes shares one throw-away cache folder, so a
scene is ray-cast at most once per session and the user's own cache is never touched."""

from __future__ import annotations

import os
import tempfile


def pytest_configure(config) -> None:
    if "MAPLESS_TEST_KEEP_CACHE" not in os.environ:
        os.environ["MAPLESS_CACHE"] = tempfile.mkdtemp(prefix="mapless-test-cache-")
