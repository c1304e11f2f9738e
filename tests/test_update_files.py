"""tools/update_files.py keeps, of the files one PPO update runs through, those a reader follows:
the environment and the named primitives go; the base class, the encoder and the learned loss stay,
each with its line count."""

from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("update_files", REPO / "tools" / "update_files.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_environment_and_the_primitives_are_left_out(monkeypatch) -> None:
    tool = _tool()
    code_map = tool._code_map()
    package = code_map.PACKAGE
    traced = [
        "train/ppo.py",
        "models/base.py",
        "models/cvmeta.py",
        "models/learned_loss.py",
        "sim/vector.py",
        "episodes/sampler.py",
        "knowledge/glove.py",
        "scenes/categories.py",
        "models/dropout.py",
        "train/loop.py",
    ]
    monkeypatch.setattr(code_map, "trace_update", lambda model: [package / name for name in traced])
    rows = tool.files_of_one_update("cvmeta")
    kept = ["train/ppo.py", "models/base.py", "models/cvmeta.py", "models/learned_loss.py"]
    assert [name for name, _ in rows] == kept
    assert [lines for _, lines in rows] == [code_map.line_count(package / name) for name in kept]
    assert all(lines > 0 for _, lines in rows)
