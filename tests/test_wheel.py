"""The wheel carries the package whole: every file under mapless/data (floor plans, grids, GloVe
vectors, priors, episode sets) and mapless/configs (budgets, recipes, experiment and training
configs), byte for byte, and the licence, so that an installed mapless runs without the checkout."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import mapless

pytestmark = pytest.mark.slow

ROOT = Path(mapless.__file__).resolve().parent.parent


def test_the_wheel_holds_every_file_of_the_package_data(tmp_path: Path) -> None:
    # Built from a copy: a build writes build/ and egg-info folders where it runs, and the working
    # tree is shared with whoever else works in it.
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, source / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "mapless", source / "mapless", ignore=ignore)
    out = tmp_path / "wheel"
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index"]
    done = subprocess.run([*command, "-q", "-w", str(out), str(source)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    (wheel,) = out.glob("mapless-*.whl")

    data = ROOT / "mapless" / "data"
    expected = {
        path.relative_to(ROOT).as_posix(): path.read_bytes()
        for path in data.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert len(expected) > 10, "the package data went missing from the checkout itself"
    with zipfile.ZipFile(wheel) as archive:
        shipped = {name for name in archive.namelist() if name.startswith("mapless/data/")}
        assert sorted(expected) == sorted(shipped)
        for name, content in expected.items():
            assert archive.read(name) == content, name
        # ... and the code beside it: every module of the package.
        modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "mapless").rglob("*.py")}
        assert modules <= set(archive.namelist())
        # ... and the licence, the full Apache-2.0 text the metadata names.
        (licence,) = [n for n in archive.namelist() if n.endswith(".dist-info/licenses/LICENSE")]
        assert archive.read(licence) == (ROOT / "LICENSE").read_bytes()
        metadata = archive.read(licence.replace("licenses/LICENSE", "METADATA")).decode()
        assert "License-Expression: Apache-2.0" in metadata.splitlines()
        assert b"Apache License\n                           Version 2.0" in archive.read(licence)
