"""The files a reader opens to follow one PPO update, counted by running one.

:func:`tools.code_map.trace_update` traces one ``PPOTrainer.update()`` of a model on the tests' tiny
fixtures (collection, GAE, the minibatches' replay, loss and backward, the optimizer steps) and
gives every ``mapless/`` file whose functions ran. :func:`files_of_one_update` keeps the ones a
reader following the update opens (:func:`tools.code_map.is_read_by_a_reader`): it leaves out the
environment and the primitives whose names say what they do; the policy's base class, its encoder
file, the learned loss φ and the LSTM cell (``models/layers.py``) count.

    python tools/update_files.py [MODEL ...]      # default: cvmeta a3c
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent


def _code_map():
    """tools/code_map.py, the tracer (tools/ is not a package)."""
    if "code_map" not in sys.modules:
        spec = importlib.util.spec_from_file_location("code_map", TOOLS / "code_map.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules["code_map"] = module
    return sys.modules["code_map"]


def files_of_one_update(model: str = "cvmeta") -> list[tuple[str, int]]:
    """``(path under mapless/, lines)`` of the files a reader opens to follow one PPO update of
    ``model``: the traced files without the environment and the primitives, sorted by path."""
    code_map = _code_map()
    rows = []
    for path in code_map.trace_update(model):
        if code_map.is_read_by_a_reader(path):
            rows.append((path.relative_to(code_map.PACKAGE).as_posix(), code_map.line_count(path)))
    return rows


def main(argv: list[str]) -> None:
    for model in argv or ["cvmeta", "a3c"]:
        rows = files_of_one_update(model)
        print(f"{model}: {len(rows)} files, {sum(lines for _, lines in rows):,} lines")
        for path, lines in rows:
            print(f"  {path:32} {lines:5}")


if __name__ == "__main__":
    main(sys.argv[1:])
