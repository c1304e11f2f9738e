"""Scene variants: the name syntax, the arrangement reader, applying an arrangement (moved where the
file says, removed objects gone), the scene cache keyed by the arrangement, bad input, and the
procedural generator (deterministic, on plausible receptacles)."""

from __future__ import annotations

import gzip
import pickle

import numpy as np
import pytest

from mapless.errors import MaplessError
from mapless.scenes.arrangements import arrangement_of, read_rearrangement
from mapless.scenes.catalogue import canonical_scene, parse_variant, resolve_scenes, room_type_of, split_of
from mapless.scenes.floor_plans import default_poses
from mapless.scenes.generator import generate, receptacle_prior
from mapless.scenes.layout import load_scene
from mapless.scenes.variants import load_variant
from mapless.sim import cache
from mapless.sim.config import SimConfig

FAST = SimConfig(ray_resolution=14)
PLAN = "FloorPlan425"  # the smallest bathroom: fast to build


def _pose(name: str, x: float, y: float, z: float, yaw: float) -> dict:
    return {
        "name": name,
        "objectName": name,
        "position": {"x": x, "y": y, "z": z},
        "rotation": {"x": 0, "y": yaw, "z": 0},
    }


def _write(path, data) -> str:
    path.write_bytes(gzip.compress(pickle.dumps(data)))
    return str(path)


def _defaults_episode(plan: str, drop: str = "", move: dict | None = None) -> dict:
    """An episode listing every pickupable object of ``plan`` at its default pivot, except ``drop``
    (left out: removed) and those in ``move`` (name -> (x, y, z, yaw))."""
    poses = []
    for obj in load_scene(plan).objects:
        if obj.pickupable and obj.name != drop:
            x, y, z, yaw = (move or {}).get(obj.name, default_poses(plan)[obj.name])
            poses.append(_pose(obj.name, x, y, z, yaw))
    return {"target_poses": poses, "starting_poses": poses, "openable_data": []}


def test_names_parse_to_canonical_form_and_keep_the_floor_plan_facts():
    assert canonical_scene("FloorPlan1_physics@rearrange2023:17") == "FloorPlan1@rearrange2023:17"
    assert canonical_scene("FloorPlan1@rearrange2023:17:target") == "FloorPlan1@rearrange2023:17"
    assert canonical_scene("FloorPlan1@rearrange2023:17:start") == "FloorPlan1@rearrange2023:17:start"
    assert str(parse_variant("FloorPlan226@gen:3")) == "FloorPlan226@gen:3"
    assert room_type_of("FloorPlan226@gen:3") == "living_room" and split_of("FloorPlan226@gen:3") == "test"
    assert resolve_scenes("FloorPlan1@gen:0,FloorPlan2") == ["FloorPlan1@gen:0", "FloorPlan2"]
    for bad in (
        "FloorPlan1@gen",
        "FloorPlan1@:3",
        "FloorPlan1@gen:x",
        "FloorPlan99@gen:1",
        "FloorPlan1@gen:1:start",
    ):
        with pytest.raises(MaplessError):
            canonical_scene(bad)


def test_the_builtin_source_is_the_rearrangement_datasets_training_split():
    data = read_rearrangement("rearrange2023")
    assert len(data) == 80 and all(len(episodes) == 50 for episodes in data.values())
    assert all(split_of(plan) == "train" for plan in data)
    arrangement = arrangement_of("rearrange2023", "FloorPlan1", 0)
    assert len(arrangement.poses) == 24  # the episode's target_poses


def test_a_moved_object_is_where_the_file_says_and_an_unlisted_one_is_gone(tmp_path):
    scene = load_scene(PLAN)
    movable = [o for o in scene.objects if o.pickupable and o.footprint is not None]
    moved, dropped = movable[0], movable[1]
    x, y, z, yaw = default_poses(PLAN)[moved.name]
    # 0.1 m along x on its own surface, turned a quarter.
    target = (x + 0.1, y, z, yaw + 90)
    source = _write(
        tmp_path / "mine.pkl.gz", {PLAN: [_defaults_episode(PLAN, dropped.name, {moved.name: target})]}
    )
    variant = load_variant(f"{PLAN}@{source}:0")
    assert dropped.id not in variant.object_index
    assert len(variant.objects) == len(scene.objects) - 1
    after = variant.object(moved.id)
    # The box centre keeps its offset from the pivot, turned by 90 degrees (+z -> +x).
    dx, dy, dz = np.subtract(moved.center, (x, y, z))
    np.testing.assert_allclose(after.center, (x + 0.1 + dz, y + dy, z - dx), atol=2e-4)
    np.testing.assert_allclose(after.size, (moved.size[2], moved.size[1], moved.size[0]), atol=2e-3)
    # Every other object is untouched.
    for obj in scene.objects:
        if obj.id not in (moved.id, dropped.id):
            assert variant.object(obj.id) == obj


def test_a_removed_object_is_absent_from_every_observation_and_goals_are_recomputed(tmp_path):
    scene = load_scene(PLAN)
    target = next(o for o in scene.objects if o.pickupable and o.type == "SoapBar")
    episode = _defaults_episode(PLAN, drop=target.name)
    source = _write(tmp_path / "drop.pkl.gz", {PLAN: [episode]})
    name = f"{PLAN}@{source}:0"
    data = cache.load_or_build(name, FAST, tmp_path)
    default = cache.load_or_build(PLAN, FAST, tmp_path)
    assert data.scene == name and data.n_poses == default.n_poses
    assert target.id not in data.instance_ids
    gone = [i for i, t in enumerate(data.instance_types) if t == "SoapBar"]
    assert len(gone) == len(default.instances_of("SoapBar")) - 1
    if not gone:
        assert not data.goal_mask("SoapBar").any() and default.goal_mask("SoapBar").any()
    # Everything else that the default layout sees is seen the same (same boxes, same order of ids).
    keep = [default.instance_ids.index(i) for i in data.instance_ids]
    np.testing.assert_array_equal(np.asarray(default.instance_ids)[keep], data.instance_ids)


def test_the_cache_key_is_the_arrangement_not_the_name(tmp_path):
    episode = read_rearrangement("rearrange2023")["FloorPlan1"][3]
    copy = _write(tmp_path / "copy.pkl.gz", {"FloorPlan1": [episode]})
    same = cache.cache_path(f"FloorPlan1@{copy}:0", FAST, tmp_path)
    assert same == cache.cache_path("FloorPlan1@rearrange2023:3", FAST, tmp_path)
    assert same != cache.cache_path("FloorPlan1@rearrange2023:3:start", FAST, tmp_path) or (
        episode["target_poses"] == episode["starting_poses"]
    )
    assert same != cache.cache_path("FloorPlan1@rearrange2023:4", FAST, tmp_path)
    assert same != cache.cache_path("FloorPlan1", FAST, tmp_path)


def test_a_variant_round_trips_through_the_cache(tmp_path, monkeypatch):
    name = f"{PLAN}@gen:1"
    built = cache.load_or_build(name, FAST, tmp_path)
    monkeypatch.setattr(cache, "build_scene_data", lambda *a, **k: pytest.fail("rebuilt a valid entry"))
    loaded = cache.load_or_build(name, FAST, tmp_path)
    assert loaded.scene == name and loaded.instance_ids == built.instance_ids
    for field in ("successors", "context", "features", "view_box", "view_visible"):
        np.testing.assert_array_equal(getattr(loaded, field), getattr(built, field))


def test_bad_arrangements_are_errors_naming_the_object(tmp_path):
    plan = "FloorPlan1"
    apple = next(o for o in load_scene(plan).objects if o.type == "Apple")
    x, y, z, yaw = default_poses(plan)[apple.name]
    ghost = _defaults_episode(plan)
    ghost["target_poses"].append(_pose("Unicorn_0000", 0, 1, 0, 0))
    floating = _defaults_episode(plan, move={apple.name: (x, y + 1.5, z, yaw)})
    other = {"target_poses": [_pose(f"Thing_{i:04d}", 0, 1, 0, 0) for i in range(10)], "openable_data": []}
    source = _write(tmp_path / "bad.pkl.gz", {plan: [ghost, floating, other]})
    with pytest.raises(MaplessError, match="Unicorn_0000"):
        load_variant(f"{plan}@{source}:0")
    with pytest.raises(MaplessError, match=f"{apple.name}.*off any surface"):
        load_variant(f"{plan}@{source}:1")
    with pytest.raises(MaplessError, match="another AI2-THOR version"):
        load_variant(f"{plan}@{source}:2")
    with pytest.raises(MaplessError, match="holds episodes 0-2 of FloorPlan1, not 7"):
        load_variant(f"{plan}@{source}:7")


def test_arrangement_files_cannot_run_code(tmp_path):
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"FloorPlan1": [{"target_poses": [np.float64(1.0)]}]}))
    with pytest.raises(MaplessError, match="refusing to load"):
        read_rearrangement(str(evil))
    with pytest.raises(MaplessError, match="cannot read arrangement file"):
        read_rearrangement(str(tmp_path / "missing.pkl.gz"))


def test_the_generator_is_deterministic_and_puts_objects_on_plausible_receptacles():
    first, again = generate("FloorPlan26", 0), generate("FloorPlan26", 0)
    assert first == again and first.digest() == again.digest()
    # Bit for bit across versions of the code: a change here must bump GENERATOR_VERSION.
    assert first.digest()[:16] == "fce400b30805f0f0"
    assert generate("FloorPlan26", 1).digest() != first.digest()
    scene, variant = load_scene("FloorPlan26"), load_variant("FloorPlan26@gen:0")
    prior = receptacle_prior("kitchen")
    moved = 0
    for obj in variant.objects:
        if not obj.pickupable:
            continue
        assert obj.parents, f"{obj.name} rests on nothing"
        support = variant.object(obj.parents[0])
        if obj.type in prior and support.type in {t for t in prior[obj.type]}:
            moved += 1
        moved_by = np.hypot(*np.subtract(obj.center, scene.object(obj.id).center)[[0, 2]])
        assert moved_by < 20  # inside the floor plan
    assert moved >= 0.8 * sum(o.pickupable for o in variant.objects)


def test_the_prior_comes_from_the_training_floor_plans_only(monkeypatch):
    from mapless.scenes import generator

    seen: list[str] = []
    original = generator.load_floor_plan
    monkeypatch.setattr(generator, "load_floor_plan", lambda name: seen.append(name) or original(name))
    generator.receptacle_prior.cache_clear()
    try:
        generator.receptacle_prior("bedroom")
    finally:
        generator.receptacle_prior.cache_clear()
    assert seen and all(split_of(name) == "train" for name in seen)
