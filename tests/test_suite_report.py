"""The suite reports what it does not run: opt-in tests show up as skipped, with their reason, in
every run of the whole suite, instead of being left out of collection."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent


def test_the_live_thor_tests_are_reported_as_skipped_with_their_reason() -> None:
    env = {k: v for k, v in os.environ.items() if k != "MAPLESS_THOR"}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            str(TESTS),
            "-q",
            "-rs",
            "-p",
            "no:cacheprovider",
            "-k",
            "thor_real",
        ],
        env=env,
        cwd=TESTS.parent,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    skipped = [
        line for line in done.stdout.splitlines() if line.startswith("SKIPPED [1] tests/test_thor_real.py")
    ]
    assert len(skipped) == 2 and all(line.endswith("opt in with MAPLESS_THOR=1") for line in skipped), (
        done.stdout
    )
