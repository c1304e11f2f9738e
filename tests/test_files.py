"""Atomic writes: the old content survives a failed write, and torn files read as errors or misses."""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from mapless.episodes import evalsets
from mapless.errors import MaplessError
from mapless.files import replacing, write_text


def test_a_failed_write_leaves_the_old_content(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "report.json"
    write_text(target, "old")
    with pytest.raises(RuntimeError), replacing(target) as tmp:
        tmp.write_text("half of the new")
        raise RuntimeError("killed mid-write")
    assert target.read_text() == "old"
    assert sorted(p.name for p in target.parent.iterdir()) == ["report.json"]  # no temporary left
    write_text(target, "new")
    assert target.read_text() == "new"


def test_a_torn_episode_file_is_a_clear_error(tmp_path: Path) -> None:
    whole = evalsets.builtin_path("val").read_bytes()
    torn = tmp_path / "val.json.gz"
    torn.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(MaplessError, match="cannot read episode file"):
        evalsets.load(torn)
    garbled = tmp_path / "garbled.json.gz"
    garbled.write_bytes(whole[:20] + bytes(len(whole) - 20))
    with pytest.raises(MaplessError, match="cannot read episode file"):
        evalsets.load(garbled)
    assert gzip.decompress(whole)  # the built-in file itself is whole
