"""The evaluation protocols: the reference protocol's 1.5 m rule on known geometry, its split, the
evaluation-set sampler under each protocol, and the pose-graph islands no episode starts on."""

from __future__ import annotations

import collections
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mapless.config import ConfigError
from mapless.episodes import evalsets
from mapless.episodes.protocols import PROTOCOLS, protocol_of_split, split_for
from mapless.episodes.sampler import TrainingSampler
from mapless.errors import UnknownNameError
from mapless.experiments.config import ExperimentConfig, ExperimentEval, train_config
from mapless.scenes.catalogue import ROOM_TYPES, SPLITS, scene_names, split_range_label
from mapless.sim.build import build_scene_data
from mapless.sim.cache import cache_path, fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import pose_key
from tests.scene_fixtures import grid_scene
from tests.synthetic import box, square_room

STANDARD, REFERENCE = PROTOCOLS["standard"], PROTOCOLS["reference"]


@pytest.mark.slow
def test_the_reference_rule_sees_one_and_a_half_metres_on_known_geometry():
    # Mugs on a counter at eye-ish height straight ahead: the capsule distance is the horizontal one.
    # Their near faces lie 1.25 m and 1.65 m away.
    near = box("Mug|1", "Mug", (0.0, 1.0, 1.3), (0.1, 0.1, 0.1), pickupable=True)
    far = box("Mug|2", "Mug", (0.3, 1.0, 1.7), (0.1, 0.1, 0.1), pickupable=True)
    scene = square_room([near, far], half_width=2.5)
    config = SimConfig(ray_resolution=42)
    standard = build_scene_data(scene, STANDARD.sim(config))
    reference = build_scene_data(scene, REFERENCE.sim(config))
    pose = standard.pose_index["0.00|0.00|0|0"]
    assert set(standard.in_view(pose).tolist()) == {0, 1}
    assert set(standard.visible(pose).tolist()) == set()  # both beyond 1.0 m
    assert set(reference.visible(pose).tolist()) == {0}  # 1.25 m within 1.5 m, 1.65 m not
    # The rule changes nothing but visibility: same poses, moves, boxes and observations.
    for name in ("successors", "view_instance", "view_box", "view_distance", "context", "features"):
        np.testing.assert_array_equal(getattr(standard, name), getattr(reference, name))


def test_both_rules_have_their_own_scene_cache():
    assert REFERENCE.sim(SimConfig()).visibility_distance == 1.5
    assert fingerprint(REFERENCE.sim(SimConfig())) != fingerprint(SimConfig())
    assert cache_path("FloorPlan1", REFERENCE.sim(SimConfig())) != cache_path("FloorPlan1", SimConfig())


def test_the_reference_split_is_the_published_one():
    def numbers(split: str, room: str) -> list[int]:
        return [int(s[len("FloorPlan") :]) % 100 for s in scene_names(split, (room,))]

    for room in ROOM_TYPES:
        assert numbers("ref_val", room) == [21, 23, 25, 27, 29]
        assert numbers("ref_test", room) == [22, 24, 26, 28, 30]
        assert sorted(numbers("ref_val", room) + numbers("ref_test", room)) == numbers("paper", room)
    assert list(SPLITS["train"]) == list(range(1, 21))  # training is the same under every protocol
    assert (split_range_label("ref_val"), split_range_label("ref_test")) == ("x21-x29 odd", "x22-x30 even")
    assert split_range_label("val") == "x21-x25"
    assert (split_for("reference", "val"), split_for("reference", "test")) == ("ref_val", "ref_test")
    assert (split_for("standard", "val"), split_for("standard", "test")) == ("val", "test")
    assert split_for("standard", "paper") == "paper" == split_for("paper", "test")
    with pytest.raises(UnknownNameError, match=r"unknown split 'tset'.*val, test, paper"):
        split_for("standard", "tset")
    assert protocol_of_split("ref_test") is REFERENCE and protocol_of_split("paper") is PROTOCOLS["paper"]


def test_a_reference_experiment_trains_under_the_reference_rule():
    standard = ExperimentConfig(train={"episodes": 10})
    reference = dataclasses.replace(standard, eval=ExperimentEval(protocol="reference"))
    assert train_config(standard, "a3c", 1).env.sim.visibility_distance == 1.0
    assert train_config(reference, "a3c", 1).env.sim.visibility_distance == 1.5
    contradicting = dataclasses.replace(reference, train={"env": {"sim": {"visibility_distance": 1.0}}})
    with pytest.raises(ConfigError, match="contradicts the reference protocol"):
        train_config(contradicting, "a3c", 1)
    # ...and on the classes of its episodes, the published ones', unless the experiment names others.
    assert train_config(reference, "a3c", 1).env.target_set == "hoz22"
    assert train_config(standard, "a3c", 1).env.target_set == "mjolnir22"
    named = dataclasses.replace(reference, train={"episodes": 10, "env": {"target_set": "savn"}})
    assert train_config(named, "a3c", 1).env.target_set == "savn"


def test_mapless_train_for_the_reference_protocol_takes_its_classes_unless_told(tmp_path: Path):
    from mapless.cli.train import protocol_overrides

    bare, named = tmp_path / "bare.yaml", tmp_path / "named.yaml"
    bare.write_text("model: {name: a3c}\n")
    named.write_text("model: {name: a3c}\nenv: {target_set: mjolnir22}\n")
    rule = "env.sim.visibility_distance=1.5"
    assert protocol_overrides("reference", bare, []) == [rule, "env.target_set=hoz22"]
    assert protocol_overrides("reference", named, []) == [rule]  # the file's choice stands
    assert protocol_overrides("reference", bare, ["env.target_set=savn"]) == [rule]
    assert protocol_overrides("standard", bare, []) == [
        "env.sim.visibility_distance=1.0",
        "env.target_set=mjolnir22",
    ]


# ------------------------------------------------------------------ samplers on a scene with an island

#: A 3x3 grid and an island position (2.0, 2.0) that no move reaches.
MAIN = tuple((0.25 * i, 0.25 * j) for i in range(3) for j in range(3))
ISLAND = (2.0, 2.0)
MUG, TOASTER = 0, 4  # instance indices in tests.scene_fixtures.INSTANCES


def _island_scene(name: str) -> object:
    """Mug 0 is visible from the main grid's corner (0, 0) facing north; Toaster only from the island."""
    data = grid_scene(positions=(*MAIN, ISLAND), blocked=(), scene=name)
    at_corner = (data.x == 0) & (data.z == 0) & (data.yaw == 0)
    at_island = data.x == ISLAND[0]
    view = [[MUG] if at_corner[p] else [TOASTER] if at_island[p] else [] for p in range(data.n_poses)]
    counts = np.array([len(v) for v in view])
    entries = int(counts.sum())
    return dataclasses.replace(
        data,
        view_ptr=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        view_instance=np.array([i for v in view for i in v], dtype=np.int32),
        view_box=np.tile(np.array([[10, 10, 50, 50]], np.float32), (entries, 1)),
        view_distance=np.full(entries, 0.5, np.float32),
        view_visible=np.ones(entries, bool),
        _distance_cache={},
    )


@pytest.fixture(scope="module")
def island_library() -> SceneLibrary:
    return SceneLibrary(lambda name: _island_scene(name))


def test_islands_are_found_and_left_out(island_library):
    data = island_library["FloorPlan5"]
    sizes = np.bincount(data.components)
    assert sizes.tolist() == [9 * 16, 16]  # the grid's poses, then the island's 8 yaws x 2 horizons
    assert not data.usable_poses[data.x == ISLAND[0]].any() and data.usable_poses[data.x < 1].all()


def test_the_training_sampler_never_starts_on_an_island(island_library):
    sampler = TrainingSampler(island_library, ["FloorPlan5"], seed=0)
    rng = np.random.default_rng(0)
    episodes = [sampler.sample(rng) for _ in range(1000)]
    # The Toaster is visible only from the island: no usable start reaches it, so it is never drawn.
    assert {e.target for e in episodes} == {"Mug"}
    assert all(e.start[0] < 1 and e.start[3] == 0 for e in episodes)
    data = island_library["FloorPlan5"]
    starts = {island_library.pose_of("FloorPlan5", e.start) for e in episodes}
    assert all(data.target_distances("Mug")[p] >= 0 for p in starts)
    assert len(starts) == int(((data.horizon == 0) & data.usable_poses).sum())  # uniform over all of them


@pytest.mark.parametrize("split", ["val", "ref_val"])
def test_evaluation_sets_sample_as_their_protocol_says(island_library, split):
    episodes = evalsets.make_eval_set(island_library, split, per_room=200, room_types=("kitchen",))
    assert len(episodes) == 200 and {e.target for e in episodes} == {"Mug"}
    assert {e.scene for e in episodes} <= set(scene_names(split, ("kitchen",)))
    assert all(e.start[0] < 1 and e.start[3] == 0 for e in episodes)  # never on the island
    in_view = [e for e in episodes if e.optimal_length == 1]  # the start already sees the target
    if protocol_of_split(split).visible_starts:
        # 1 of the grid's 72 horizon-0 starts sees the mug: about 3 of 200 draws.
        assert in_view and all(e.start == (0.0, 0.0, 0, 0) for e in in_view)
    else:
        assert not in_view and min(e.optimal_length for e in episodes) == 2


@pytest.mark.parametrize("split", ["ref_val", "ref_test"])
def test_shipped_reference_sets_follow_the_protocol(split):
    episodes, header = evalsets.load(
        evalsets.builtin_path(split), expected_fingerprint=fingerprint(REFERENCE.sim(SimConfig()))
    )
    assert header["scenes"] == split_range_label(split) and len(episodes) == 1000
    by_room = {room: [e for e in episodes if e.episode_id.split("/")[1] == room] for room in ROOM_TYPES}
    assert all(len(eps) == 250 for eps in by_room.values())
    for room, eps in by_room.items():
        assert {e.scene for e in eps} <= set(scene_names(split, (room,)))
    lengths = np.array([e.optimal_length for e in episodes])
    assert lengths.min() == 1 and 0.02 < (lengths == 1).mean() < 0.2  # some starts see the target
    assert all(e.start[3] == 0 for e in episodes)


# ------------------------------------------------------------- the published episodes (HOZ, 22 classes)

#: Mapped episodes per room type of the shipped published sets (the mapping report, docs/guide/interop.md).
PUBLISHED_MAPPED = {
    "ref_val": {"kitchen": 864, "living_room": 927, "bedroom": 937, "bathroom": 996},
    "ref_test": {"kitchen": 922, "living_room": 1000, "bedroom": 959, "bathroom": 861},
}


def test_the_training_target_set_decides_which_sets_are_read():
    # The reference protocol reads the sets of the model's training target set: the sampled sets of
    # mjolnir22 (the default), the published HOZ episodes of hoz22 (tests/test_target_sets.py).
    assert evalsets.set_path("ref_test").name == "ref_test_mjolnir22.json.gz"
    assert evalsets.set_path("ref_val", "hoz22").name == "ref_val_hoz22.json.gz"
    assert evalsets.set_path("ref_val", "savn").name == "ref_val_savn.json.gz"
    assert evalsets.set_path("test").name == "test_mjolnir22.json.gz"
    # A shipped set by name, whatever the target set; a path stays a path.
    hoz = evalsets.set_path("ref_test", episodes_file="ref_test_hoz22")
    assert hoz == evalsets.builtin_path("ref_test", "hoz22") and hoz.is_file()
    assert evalsets.set_path("ref_test", episodes_file="x/ref_test_hoz22") == Path("x/ref_test_hoz22")
    assert evalsets.set_path("ref_test", layouts="gen:3").name == "ref_test_gen3_mjolnir22.json.gz"


@pytest.mark.parametrize("split", ["ref_val", "ref_test"])
def test_the_shipped_published_sets_are_their_files_mapped(split):
    from mapless.offline.episodes import map_episodes, read_episode_file

    episodes, header = evalsets.load(
        evalsets.set_path(split, "hoz22"), fingerprint(REFERENCE.sim(SimConfig()))
    )
    assert (header["split"], header["target_set"]) == (split, "hoz22")
    rooms = [e.episode_id.split("/")[1] for e in episodes]
    assert collections.Counter(rooms) == PUBLISHED_MAPPED[split]
    assert rooms == sorted(rooms, key=ROOM_TYPES.index)  # room by room, each in its file's order
    for room in ROOM_TYPES:
        raw = read_episode_file(evalsets.published_path("hoz22", split, room))[0]
        # The target ids do not depend on the simulator: the layout-level mapping gives the same.
        layout = {
            e.episode_id: e
            for e in map_episodes(raw, max_start_distance=10.0, id_prefix=f"hoz22_{split[4:]}").episodes
        }
        mapped = [e for e in episodes if e.episode_id.split("/")[1] == room]
        indices = [int(e.episode_id.rsplit("/", 1)[1]) for e in mapped]
        assert indices == sorted(indices)
        for e in mapped:
            published = raw[int(e.episode_id.rsplit("/", 1)[1])]
            assert e.target_ids == layout[e.episode_id].target_ids and e.optimal_length >= 1
            assert e.start[2:] == published.start[2:]
            assert np.hypot(e.start[0] - published.start[0], e.start[1] - published.start[1]) <= 0.36


@pytest.mark.slow
def test_the_published_sets_map_exactly_onto_a_built_scene():
    # FloorPlan424 built here under the reference rule: mapping its published test episodes gives the
    # shipped episodes, optimal lengths included.
    from mapless.offline.episodes import map_episodes, read_episode_file
    from mapless.scenes import load_scene

    data = build_scene_data(load_scene("FloorPlan424"), REFERENCE.sim(SimConfig()))
    raw = [
        e
        for e in read_episode_file(evalsets.published_path("hoz22", "ref_test", "bathroom"))[0]
        if e.scene == "FloorPlan424"
    ]
    report = map_episodes(raw, scene_data=lambda name: data, id_prefix="hoz22_test")
    shipped = [
        e for e in evalsets.load(evalsets.set_path("ref_test", "hoz22"))[0] if e.scene == "FloorPlan424"
    ]
    assert report.episodes == shipped and len(shipped) == report.total == 200
    for e in shipped:
        goal = data.goal_mask_for_instances(np.array([data.instance_ids.index(i) for i in e.target_ids]))
        assert e.optimal_length == data.distances_to(goal)[data.pose_index[pose_key(*e.start)]] + 1


def test_per_room_keeps_the_first_episodes_of_each_published_file():
    from mapless.evaluate.episode_sets import load_episodes

    episodes = load_episodes("ref_test", per_room=250, target_set="hoz22")
    assert collections.Counter(e.episode_id.split("/")[1] for e in episodes) == dict.fromkeys(ROOM_TYPES, 250)
    full = load_episodes("ref_test", target_set="hoz22")
    assert episodes == [
        e for room in ROOM_TYPES for e in [f for f in full if f.episode_id.split("/")[1] == room][:250]
    ]
    assert len(full) == sum(PUBLISHED_MAPPED["ref_test"].values())
