"""The scene cache: reuse, rebuild of stale or corrupt entries, atomic files, parameter hashing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from damage import one_byte_flips

from mapless.sim import cache
from mapless.sim.config import SimConfig

SCENE = "FloorPlan425"  # the smallest bathroom
FAST = SimConfig(ray_resolution=14)


def test_load_returns_what_was_built_and_reuses_the_file(tmp_path, monkeypatch):
    built = cache.load_or_build(SCENE, FAST, tmp_path)
    path = cache.cache_path(SCENE, FAST, tmp_path)
    assert path.exists() and not list(path.parent.glob("*.tmp"))
    monkeypatch.setattr(cache, "build_scene_data", lambda *a, **k: pytest.fail("rebuilt a valid entry"))
    loaded = cache.load_or_build(SCENE, FAST, tmp_path)
    for name in ("successors", "context", "features", "view_box", "view_visible"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(built, name))
    assert loaded.instance_ids == built.instance_ids


def test_every_parameter_changes_the_fingerprint():
    base = cache.fingerprint(FAST)
    for change in (
        {"visibility_distance": 1.5},
        {"horizons": (-30, 0, 30)},
        {"eye_height": 1.5},
        {"horizontal_fov": 100.0},
        {"strict_diagonals": True},
    ):
        assert cache.fingerprint(SimConfig(**{**FAST.as_dict(), **change})) != base


def test_fields_added_later_keep_the_fingerprints_made_before_them():
    # The shipped episode sets record the default simulator's fingerprint of before strict_diagonals.
    from mapless.episodes import evalsets

    assert evalsets.load(evalsets.builtin_path("test"))[1]["sim_fingerprint"] == cache.fingerprint(
        SimConfig()
    )


@pytest.mark.parametrize(
    "damage", ["truncate", "garbage", "other_fingerprint", "flipped_array", "other_scene"]
)
def test_damaged_entries_are_detected_and_rebuilt(tmp_path, damage):
    original = cache.load_or_build(SCENE, FAST, tmp_path)
    path = cache.cache_path(SCENE, FAST, tmp_path)
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:1000])
    elif damage == "garbage":
        path.write_bytes(b"not a zip file")
    else:
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        header = json.loads(str(arrays["header"]))
        if damage == "other_fingerprint":
            header["fingerprint"] = "0" * 16
        elif damage == "other_scene":  # another scene's valid file copied over this one's
            header["scene"] = "FloorPlan424"
        else:
            arrays["successors"] = arrays["successors"][::-1].copy()
        arrays["header"] = np.array(json.dumps(header))
        np.savez(path.with_suffix(""), **arrays)
        path.with_suffix("").with_suffix(".npz").replace(path)
    with pytest.raises(cache.StaleCacheError):
        cache.load(path, FAST)
    rebuilt = cache.load_or_build(SCENE, FAST, tmp_path)
    np.testing.assert_array_equal(rebuilt.successors, original.successors)
    cache.load(path, FAST)  # the rebuilt file is valid again


@pytest.mark.slow
def test_prepare_builds_only_the_missing_scenes_before_first_use(tmp_path):
    from mapless.sim.library import SceneLibrary

    cache.load_or_build(SCENE, FAST, tmp_path)
    kept = cache.cache_path(SCENE, FAST, tmp_path)
    stamp = kept.stat().st_mtime_ns
    library = SceneLibrary.builtin(FAST, tmp_path)
    library.prepare([SCENE, "FloorPlan25", SCENE], progress=False)
    added = cache.cache_path("FloorPlan25", FAST, tmp_path)
    assert added.exists()
    assert kept.stat().st_mtime_ns == stamp  # the existing file was neither rebuilt nor rewritten
    stamps = [kept.stat().st_mtime_ns, added.stat().st_mtime_ns]
    library.prepare([SCENE, "FloorPlan25"], progress=False)
    assert cache.build_many([SCENE, "FloorPlan25"], FAST, tmp_path, missing_only=True) == []
    assert [kept.stat().st_mtime_ns, added.stat().st_mtime_ns] == stamps


def test_every_one_byte_flip_is_detected_or_harmless(tmp_path):
    """Random one-byte flips anywhere in a cached scene (the deflate streams included): loading
    either raises StaleCacheError, which load_or_build answers by rebuilding, or returns the data."""
    original = cache.load_or_build(SCENE, FAST, tmp_path)
    path = cache.cache_path(SCENE, FAST, tmp_path)
    detected = 0
    for _ in one_byte_flips(path, 60):
        try:
            loaded = cache.load(path, FAST)
        except cache.StaleCacheError:
            detected += 1
            continue
        np.testing.assert_array_equal(loaded.successors, original.successors)
    assert detected > 0
