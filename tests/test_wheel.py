"""The wheel carries the package whole: every file under mapless/data (floor plans, grids, GloVe
vectors, priors, episode sets) and mapless/configs (budgets, recipes, experiment and training
configs), byte for byte, and the licence, so that an installed mapless runs without the checkout."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import mapless

pytestmark = pytest.mark.slow

ROOT = Path(mapless.__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Built from a copy: a build writes build/ and egg-info folders where it runs, and the working
    # tree is shared with whoever else works in it.
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, source / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "mapless", source / "mapless", ignore=ignore)
    out = tmp_path_factory.mktemp("wheel")
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index"]
    done = subprocess.run([*command, "-q", "-w", str(out), str(source)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    (built,) = out.glob("mapless-*.whl")
    return built


def test_the_wheel_holds_every_file_of_the_package_data(wheel: Path) -> None:
    folders = (ROOT / "mapless" / "data", ROOT / "mapless" / "configs")
    expected = {
        path.relative_to(ROOT).as_posix(): path.read_bytes()
        for folder in folders
        for path in folder.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }
    assert len(expected) > 40, "the package data went missing from the checkout itself"
    assert "mapless/configs/budgets/smoke.yaml" in expected
    with zipfile.ZipFile(wheel) as archive:
        shipped = {
            name for name in archive.namelist() if name.startswith(("mapless/data/", "mapless/configs/"))
        }
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


def test_the_installed_wheel_reproduces_table1_from_an_empty_folder(wheel: Path, tmp_path: Path) -> None:
    """In a fresh venv that sees this environment's torch (and nothing of the checkout), installed
    offline from the wheel alone, `mapless reproduce table1 --budget smoke` runs from an empty folder:
    the configs, recipes and package data come from the installed package. Two of the smoke budget's
    nine models, one training floor plan and the kitchens only, for a test's time; the rest of the
    budget as shipped."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = venv / "bin" / "python"
    pip = [str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--force-reinstall"]
    done = subprocess.run([*pip, str(wheel)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    empty = tmp_path / "empty"
    empty.mkdir()
    # The checkout's mapless (installed editable here) must not be what runs.
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    where = subprocess.run(
        [str(python), "-c", "import mapless; print(mapless.__file__)"], cwd=empty, env=env,
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert Path(where.stdout.strip()).is_relative_to(venv)
    restrict = ["models=[random,a3c]", "focus=a3c", "train.env.scenes=FloorPlan1", "eval.rooms=[kitchen]"]
    command = [str(venv / "bin" / "mapless"), "reproduce", "table1", "--budget", "smoke", "--jobs", "1"]
    done = subprocess.run(
        [*command, *(a for item in restrict for a in ("--set", item))], cwd=empty, env=env,
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, (done.stdout[-2000:], done.stderr[-3000:])
    report = (empty / "reports" / "table1" / "table1.md").read_text()
    assert "| random |" in report and "| a3c |" in report
    assert sorted(p.name.split("__")[0] for p in (empty / "runs" / "experiments" / "smoke").iterdir()) == [
        "a3c"
    ]
