"""Provenance: every report and every run folder's config names the commit, the versions and the
machine's share that made it, in a checkout and outside one."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch
import yaml

import mapless
from mapless import provenance as prov
from mapless.config import load_config, save_config
from mapless.evaluate.report import write_report_files
from mapless.train.config import TrainConfig

REPO = Path(mapless.__file__).resolve().parent.parent


def _git(*args: str, cwd: Path = REPO) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture
def package_at(monkeypatch):
    """Pretend the package runs from another folder (its git look-ups are cached per process)."""

    def move(folder: Path) -> None:
        monkeypatch.setattr(prov, "_PACKAGE_DIR", folder)
        prov._git.cache_clear()

    yield move
    prov._git.cache_clear()


def test_in_this_checkout_the_record_names_head_and_the_machine() -> None:
    record = prov.provenance()
    if (REPO / ".git").exists():
        assert record["commit"] == _git("rev-parse", "HEAD")
        assert record["dirty"] == bool(_git("status", "--porcelain", "--untracked-files=no"))
    assert record["version"] == mapless.__version__ and record["torch"] == torch.__version__
    assert record["threads"] == torch.get_num_threads() and record["cores"] >= 1
    assert prov.provenance(threads=3)["threads"] == 3


def test_outside_a_checkout_or_inside_someone_elses_the_commit_is_unknown(tmp_path, package_at) -> None:
    package_at(tmp_path / "site-packages" / "mapless")
    record = prov.provenance()
    assert record["commit"] is None and record["dirty"] is None
    assert "commit unknown" in prov.describe(record)
    # A wheel installed in a virtual environment that lies inside the user's own repository: that
    # repository's commit is not the code that ran.
    other = tmp_path / "project"
    (other / "venv" / "mapless").mkdir(parents=True)
    _git("init", "-q", cwd=other)
    _git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "x", cwd=other)
    package_at(other / "venv" / "mapless")
    assert prov.git_state() == (None, None)
    # ... whereas a checkout of mapless itself (the package folder at its root) is named.
    package_at(other / "mapless")
    commit, dirty = prov.git_state()
    assert commit == _git("rev-parse", "HEAD", cwd=other) and dirty is False


def test_a_run_config_starts_with_its_provenance_and_still_loads(tmp_path: Path) -> None:
    config = TrainConfig(episodes=8)
    path = tmp_path / "config.yaml"
    save_config(config, path, prov.provenance_comment(threads=1))
    assert load_config(TrainConfig, path) == config
    first, second = path.read_text().splitlines()[:2]
    assert first.startswith("# Trained by mapless") and "1 thread(s)" in first
    record = yaml.safe_load(second.removeprefix("# "))["provenance"]
    assert record == {**prov.provenance(), "threads": 1}


def test_a_report_carries_provenance_in_json_and_markdown(tmp_path: Path) -> None:
    payload, text = write_report_files({"model": "x"}, "# title\n", tmp_path / "val")
    stored = json.loads((tmp_path / "val.json").read_text())
    assert stored == payload and stored["provenance"] == prov.provenance()
    assert (tmp_path / "val.md").read_text() == text
    assert text.endswith(f"Made by {prov.describe(prov.provenance())}.\n")


def test_a_benchmark_report_carries_the_command_its_date_and_commit(monkeypatch, tmp_path) -> None:
    """bench/ reports carry the provenance experiment reports carry: the command as a reader types
    it (the script's path relative to the working folder, not the machine's), when it finished, and
    the code it ran."""
    import re

    from mapless.provenance import command_line, git_state, stamp, stamped

    monkeypatch.chdir(tmp_path)
    script = tmp_path / "bench" / "learning_curve.py"
    assert (
        command_line([str(script), "--out", "reports/x y"])
        == "python bench/learning_curve.py --out 'reports/x y'"
    )
    assert command_line(["bench/x.py"]) == "python bench/x.py"
    record = stamped({"runs": [1]}, "python bench/x.py", threads=1)
    assert record["runs"] == [1] and record["command"] == "python bench/x.py"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d", record["finished"])
    assert record["provenance"]["commit"] == git_state()[0] and record["provenance"]["threads"] == 1
    assert re.fullmatch(r"Command: `mapless x`; finished \d{4}-\d\d-\d\d \d\d:\d\d\.", stamp("mapless x"))
