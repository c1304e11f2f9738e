"""The Python API: ``import mapless`` offers the tutorial's names without importing torch, and
docs/guide/tutorial.md runs as written, its code blocks in order, in an empty folder."""

from __future__ import annotations

import itertools
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import mapless

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "guide" / "tutorial.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```$", text, flags=re.MULTILINE | re.DOTALL)


def test_the_block_reader_takes_python_blocks_only_in_order() -> None:
    text = "```python\na = 1\n```\n\n```bash\nls\n```\ntext\n```python\nb = a + 1\n```\n"
    assert python_blocks(text) == ["a = 1\n", "b = a + 1\n"]


@pytest.mark.slow
def test_import_mapless_imports_no_torch_and_every_public_name_resolves() -> None:
    probe = "import sys, mapless; print('torch' in sys.modules, 'mapless.train' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
    for name in mapless.__all__:
        assert getattr(mapless, name) is not None, name
    assert mapless.train_model.__module__ == "mapless.train.run"
    assert mapless.evaluate_agent.__module__ == "mapless.evaluate.runner"
    assert set(mapless.__all__) <= set(dir(mapless))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = mapless.nope


@pytest.mark.slow
def test_the_tutorial_runs_as_written(tmp_path: Path, monkeypatch, single_torch_thread) -> None:
    blocks = python_blocks(TUTORIAL.read_text())
    assert len(blocks) == 5  # environment, training, evaluation, comparison, pictures
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "tutorial"}
    for number, block in enumerate(blocks, 1):
        exec(compile(block, f"{TUTORIAL.name}, block {number}", "exec"), namespace)
    # What each step left behind.
    frame = np.asarray(Image.open("frame.png"))
    assert frame.shape == (256, 256, 3)
    assert (tmp_path / "runs" / "tutorial" / "final_model.pt").is_file()
    assert namespace["summary"]["frames"] >= 1024
    assert len(namespace["trained"].results) == len(namespace["baseline"].results) == 40
    assert {r.room_type for r in namespace["trained"].results} == {"kitchen", "bathroom"}
    assert Image.open("episode.png").size[0] > Image.open("episode.png").size[1]  # two panels side by side
    first = namespace["trained"].results[0]
    path = (first.start_pose, *first.poses)
    # Pillow folds a step that changed nothing (a failed move, the Done) into the frame before it.
    assert Image.open("episode.gif").n_frames == 1 + sum(a != b for a, b in itertools.pairwise(path))
