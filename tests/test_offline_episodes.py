"""Published episode pickles: reading without the original classes, mapping, writing."""

from __future__ import annotations

import collections
import dataclasses
import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from mapless.episodes import Episode
from mapless.offline import OfflineFormatError, import_episode_file, offline_library, read_episode_file
from mapless.offline.episode_writer import write_episode_file
from mapless.offline.episodes import SKIP_CAUSES, RawEpisode, map_episodes
from mapless.sim.scene_data import pose_key

#: 50 of the 1000 published HOZ bathroom validation episodes, in their original pickle format
#: (provenance, licence and how they were cut: tests/data/README.md).
SAMPLE = Path(__file__).resolve().parent / "data" / "hoz_bathroom_val_22_sample.pkl"


@pytest.fixture(scope="module")
def sample() -> Path:
    if not SAMPLE.is_file():  # part of the repository: missing data is a failure, not a skip
        pytest.fail(f"test data missing: {SAMPLE} (see tests/data/README.md)")
    return SAMPLE


@pytest.fixture(scope="module")
def floorplan425():
    from mapless.scenes import load_scene
    from mapless.sim.build import build_scene_data
    from mapless.sim.config import SimConfig

    return build_scene_data(load_scene("FloorPlan425"), SimConfig())


def test_hoz_sample_maps_onto_built_in_scenes(sample):
    # The sample holds 50 episodes (the full file 1000); one of them, #49 (#812 of the full file),
    # starts on a pose that is not reachable and is the only one skipped, so 49 map.
    episodes, bad = read_episode_file(sample)
    assert len(episodes) == 50 and not bad
    first = episodes[0]
    assert (first.scene, first.target_type, first.start) == (
        "FloorPlan427",
        "GarbageCan",
        (-1.5, 1.0, 180, 30),
    )
    assert first.embedding.shape == (60, 1)
    report = import_episode_file(sample)
    assert report.total == 50 and report.mapped + len(report.skipped) == 50
    assert report.mapped >= 49  # all 22 target ids of the full file have a same-type object within 0.3 m
    assert report.exact_ids > 0 and report.nearest_ids > 0
    assert "episodes mapped" in report.summary()
    for index, reason in report.skipped:
        assert isinstance(index, int) and reason
    ep = report.episodes[0]
    assert (ep.scene, ep.target, ep.episode_id) == ("FloorPlan427", "GarbageCan", "import/bathroom/0000")
    assert ep.start == (-1.5, 1.0, 180, 30) and ep.optimal_length == -1  # no SceneData given
    from mapless.scenes import load_scene

    assert all(t in load_scene(ep.scene).object_index for t in ep.target_ids)


def test_unmappable_episodes_are_listed():
    # FloorPlan401 has two ToiletPaper objects, neither near (40, 40).
    raw = [
        RawEpisode(0, "FloorPlan999", "Mug", ("Mug|+00.00|+00.00|+00.00",), (0.0, 0.0, 0, 0)),
        RawEpisode(1, "FloorPlan401", "Mug", ("Mug|+00.00|+00.00|+00.00",), (0.0, 0.0, 0, 0)),
        RawEpisode(2, "FloorPlan401", "ToiletPaper", ("ToiletPaper|+40.00|+00.00|+40.00",), (0.0, 0.0, 0, 0)),
        RawEpisode(3, "FloorPlan401", "Toilet", ("Toilet|+40.00|+00.00|+40.00",), (0.0, 0.0, 10, 0)),
        RawEpisode(4, "FloorPlan401", "Toilet", (), (0.0, 0.0, 0, 0)),
        RawEpisode(5, "FloorPlan401", "Toilet", ("Toilet",), (0.0, 0.0, 0, 0)),
        RawEpisode(6, "FloorPlan401", "Toilet", ("Toilet|+40.00|+00.00|+40.00",), (40.0, 40.0, 0, 0)),
    ]
    report = map_episodes(raw)
    reasons = dict(report.skipped)
    assert report.mapped == 0 and len(reasons) == 7
    assert reasons[0].startswith("unknown scene")
    assert reasons[1].startswith("no object of that type in the scene")
    assert reasons[2].startswith("no object of that type nearby")
    assert reasons[3].startswith("start yaw not on the grid")
    assert reasons[4] == "no target: task_data is empty"
    assert reasons[5] == "target id without a position: 'Toilet'"
    assert reasons[6] == "start pose not reachable: 40.00|40.00|0|0 in FloorPlan401"
    assert report.causes() == {
        "unknown scene": 1,
        "no object of that type in the scene": 1,
        "no object of that type nearby": 1,
        "start yaw not on the grid": 1,
        "no target": 1,
        "target id without a position": 1,
        "start pose not reachable": 1,
    }
    assert set(report.causes()) <= set(SKIP_CAUSES)


def test_target_ids_that_moved_between_versions_or_are_missing(monkeypatch):
    """The target-id causes on ids of the published HOZ files (mapless/data/episodes/hoz22)."""
    start = (0.0, 0.0, 0, 0)
    # The GarbageCan of FloorPlan426 lies 1.73 m from the published one; both are the only one.
    moved = RawEpisode(0, "FloorPlan426", "GarbageCan", ("GarbageCan|-00.85|+00.00|+03.15",), start)
    # Six chairs in FloorPlan221's list, two of which AI2-THOR 5 lacks (the nearest is 3.9 m away).
    chairs = (
        "Chair|+00.77|+00.09|-01.15", "Chair|+00.77|+00.09|-02.46", "Chair|-03.07|+00.09|-00.88",
        "Chair|-03.07|+00.09|-01.52", "Chair|-03.79|+00.09|-00.84", "Chair|-03.81|+00.09|-01.55",
    )  # fmt: skip
    dropped = RawEpisode(1, "FloorPlan221", "Chair", chairs, start)
    # One of FloorPlan224's four chairs alone, 1.25 m from the nearest of the scene's three.
    far = RawEpisode(2, "FloorPlan224", "Chair", ("Chair|+03.14|+00.02|-01.63",), start)
    absent = RawEpisode(3, "FloorPlan22", "Chair", ("Chair|+01.07|+00.00|+01.56",), start)
    report = map_episodes([moved, dropped, far, absent], max_start_distance=10.0)
    assert [e.episode_id for e in report.episodes] == ["import/bathroom/0000", "import/living_room/0001"]
    assert report.episodes[0].target_ids == ("GarbageCan|-02.11|00.00|+01.96",)
    assert report.episodes[1].target_ids == (
        "Chair|-03.07|+00.10|-00.88", "Chair|-03.07|+00.10|-01.52",
        "Chair|-03.79|+00.10|-00.84", "Chair|-03.81|+00.10|-01.55",
    )  # fmt: skip
    assert (report.moved_ids, report.dropped_ids, report.nearest_ids, report.exact_ids) == (1, 2, 4, 0)
    reasons = dict(report.skipped)
    assert reasons[2].startswith(
        "no object of that type nearby: nearest 'Chair|+02.04|+00.03|-02.23' is 1.25 m"
    )
    assert reasons[3].startswith("no object of that type in the scene: Chair")
    # Without the moved-instance rule's premise (one listed, one in the scene) nothing far maps.
    two = RawEpisode(
        4, "FloorPlan426", "GarbageCan", ("GarbageCan|-00.85|+00.00|+03.15", "GarbageCan|+9|+0|+9"), start
    )
    assert dict(map_episodes([two]).skipped)[4].startswith("no object of that type nearby")


@pytest.fixture(scope="module")
def published() -> dict[str, list[RawEpisode]]:
    """The eight shipped published files, read."""
    from mapless.episodes.evalsets import PUBLISHED, published_path
    from mapless.scenes.catalogue import ROOM_TYPES

    files = {}
    for room in ROOM_TYPES:
        for split in PUBLISHED["hoz22"][1]:
            path = published_path("hoz22", split, room)
            episodes, bad = read_episode_file(path)
            assert not bad
            files[path.name] = episodes
    return files


def test_the_shipped_published_files_are_the_published_bytes():
    import gzip
    import hashlib

    from mapless.episodes.evalsets import published_path

    # sha256 of sx-zhang/HOZ @ dd5871fc test_val_split/*_22.pkl (mapless/data/NOTICE.md).
    expected = {
        ("kitchen", "ref_val"): "47f30f4b51a09129f235bdc06b01deb7f2b36627ab596728904a0a497706de91",
        ("kitchen", "ref_test"): "81f31226600fea9338b999db81b688185c6bc01421199aad8cf40d4cdaaef7eb",
        ("living_room", "ref_val"): "6d7ffeca5c4baf91a3b003af7151b659c9582d7708144ea88712d511eeea1277",
        ("living_room", "ref_test"): "d500c951a1f1d9b63477918722db839fc10302b3ffb9ab5856602f08a4c4e73e",
        ("bedroom", "ref_val"): "ee584fcebf58ba11b13cc737093952572a2a9b7bf0aece570d7d950e19e2221d",
        ("bedroom", "ref_test"): "200556d0db5a69bc7fb21ffd46cf6f529e68bbffb8cef27563dfd92fda589c8b",
        ("bathroom", "ref_val"): "a06bc6dcf638e309a04e1a52fa4e2ed681f062aa7df5dd5ddd905a59721bdcf6",
        ("bathroom", "ref_test"): "f3a1b99fd9c878ef75060a9498af566075aa83d13716f9fd6fdc6671315aad54",
    }
    for (room, split), digest in expected.items():
        data = gzip.decompress(published_path("hoz22", split, room).read_bytes())
        assert hashlib.sha256(data).hexdigest() == digest, (room, split)


def test_published_target_ids_map_by_the_documented_rules(published):
    # Layout level (no simulator): how every target id of the 8,000 published episodes matches.
    # The lists name every instance of the type: one list per scene and type throughout.
    lists = {}
    for episodes in published.values():
        for e in episodes:
            assert lists.setdefault((e.scene, e.target_type), e.target_ids) == e.target_ids
    reports = {name: map_episodes(episodes, max_start_distance=10.0) for name, episodes in published.items()}
    total = {
        k: sum(getattr(r, k) for r in reports.values())
        for k in ("exact_ids", "nearest_ids", "moved_ids", "dropped_ids")
    }
    assert total == {"exact_ids": 8898, "nearest_ids": 4745, "moved_ids": 182, "dropped_ids": 279}
    skipped = collections.Counter(r for report in reports.values() for r in report.causes().elements())
    # Only the chairs AI2-THOR 5 removed from FloorPlan22, 24 and 25 have no counterpart.
    assert skipped == {"no object of that type in the scene": 34}


class ThorAgentState:
    """What SAVN's class looks like to pickle: plain attributes."""

    def __init__(self, x, y, z, rotation, horizon):
        self.x, self.y, self.z, self.rotation, self.horizon = x, y, z, rotation, horizon


@pytest.fixture
def savn_module(monkeypatch):
    """Make ``datasets.offline_controller_with_small_rotation.ThorAgentState`` importable."""
    package = types.ModuleType("datasets")
    module = types.ModuleType("datasets.offline_controller_with_small_rotation")
    ThorAgentState.__module__ = module.__name__
    module.ThorAgentState = ThorAgentState
    package.offline_controller_with_small_rotation = module
    monkeypatch.setitem(sys.modules, "datasets", package)
    monkeypatch.setitem(sys.modules, module.__name__, module)
    return module


def test_reads_savn_pickle_without_its_classes(tmp_path, savn_module):
    glove = torch.arange(300, dtype=torch.float32)
    entries = [
        {
            "scene": "FloorPlan28_physics",
            "goal_object_type": "Box",
            "task_data": ["Box|-02.27|+00.00|-03.55"],
            "state": ThorAgentState(-1.25, 0.91, 1.75, 225, 0),
            "glove_embedding": glove,
        }
    ]
    path = tmp_path / "kitchen_test.pkl"
    path.write_bytes(pickle.dumps(entries, protocol=2))
    for name in ("datasets", savn_module.__name__):
        sys.modules.pop(name)  # the reader must not need the class
    episodes, bad = read_episode_file(path)
    assert not bad
    assert episodes[0].start == (-1.25, 1.75, 225, 0) and episodes[0].scene == "FloorPlan28_physics"
    np.testing.assert_array_equal(episodes[0].embedding, glove.numpy())


def test_written_pickles_load_in_the_originals(tmp_path, savn_module):
    episodes = [
        Episode("FloorPlan28", "Toaster", (-1.25, 1.75, 225, 0), 7, ("Toaster|+01.00|+00.90|-02.00",)),
        Episode("FloorPlan423", "Towel", (0.5, 0.25, 0, 30)),
    ]
    glove = {"Toaster": np.full(300, 0.5), "Towel": np.full(300, -0.25)}
    for fmt in ("savn", "mjolnir"):
        path = tmp_path / f"{fmt}.pkl"
        assert write_episode_file(episodes, path, fmt, embeddings=glove) == 2
        loaded = pickle.loads(path.read_bytes())  # what the original code does
        state = loaded[0]["state"]
        assert isinstance(state, savn_module.ThorAgentState)
        assert (state.x, state.z, state.rotation, state.horizon) == (-1.25, 1.75, 225, 0)
        assert loaded[0]["task_data"] == ["Toaster|+01.00|+00.90|-02.00"]
        assert loaded[1]["task_data"] and all(t.startswith("Towel|") for t in loaded[1]["task_data"])
        assert loaded[0]["goal_object_type"] == "Toaster"
        if fmt == "savn":
            assert [e["scene"] for e in loaded] == ["FloorPlan28_physics", "FloorPlan423"]
            assert isinstance(loaded[0]["glove_embedding"], torch.Tensor)
            assert "room" not in loaded[0]
        else:
            assert [e["scene"] for e in loaded] == ["FloorPlan28", "FloorPlan423"]
            assert [e["room"] for e in loaded] == ["Kitchen", "Bathroom"]
        np.testing.assert_allclose(np.asarray(loaded[1]["glove_embedding"]), -0.25)
        back, bad = read_episode_file(path)
        assert not bad and [b.start for b in back] == [(-1.25, 1.75, 225, 0), (0.5, 0.25, 0, 30)]


def test_missing_embedding_is_an_error(tmp_path):
    episode = Episode("FloorPlan28", "Toaster", (0.0, 0.0, 0, 0))
    with pytest.raises(Exception, match="no embedding for target type 'Toaster'"):
        write_episode_file([episode], tmp_path / "x.pkl", embeddings={})


class _Exploit:
    def __init__(self, target: Path):
        self.target = target

    def __reduce__(self):
        return (self.target.touch, ())


def test_unpickler_runs_no_code(tmp_path):
    path = tmp_path / "evil.pkl"
    target = tmp_path / "mapless-should-not-exist"  # inside the test's folder, not a fixed outside path
    path.write_bytes(
        pickle.dumps(
            [
                {
                    "scene": "FloorPlan1",
                    "goal_object_type": "Mug",
                    "task_data": [],
                    "state": "0.00|0.00|0|0",
                    "glove_embedding": _Exploit(target),
                }
            ]
        )
    )
    episodes, _ = read_episode_file(path)
    assert not target.exists()
    assert episodes[0].embedding is None or episodes[0].embedding.dtype != object


def test_bad_episode_files(tmp_path):
    with pytest.raises(OfflineFormatError, match="no such episode file"):
        read_episode_file(tmp_path / "missing.pkl")
    garbage = tmp_path / "garbage.pkl"
    garbage.write_bytes(b"\x80\x04not a pickle")
    with pytest.raises(OfflineFormatError, match=r"garbage\.pkl: not a readable episode pickle"):
        read_episode_file(garbage)
    wrong = tmp_path / "wrong.pkl"
    wrong.write_bytes(pickle.dumps({"scene": "FloorPlan1"}))
    with pytest.raises(OfflineFormatError, match="expected a list of episode dicts"):
        read_episode_file(wrong)
    partial = tmp_path / "partial.pkl"
    partial.write_bytes(
        pickle.dumps(
            [
                {"scene": "FloorPlan1"},
                {"scene": "FloorPlan1", "goal_object_type": "Mug", "task_data": [], "state": "bad"},
            ]
        )
    )
    episodes, bad = read_episode_file(partial)
    assert not episodes and [i for i, _ in bad] == [0, 1]
    assert "no goal_object_type, task_data, state" in bad[0][1]


def test_mapping_against_built_scene_data(sample, floorplan425):
    episodes, _ = read_episode_file(sample)
    episodes = [e for e in episodes if e.scene == "FloorPlan425"][:40]
    data = floorplan425
    report = map_episodes(episodes, scene_data=lambda name: data)
    assert report.total == 40 and report.mapped + len(report.skipped) == 40 and report.mapped >= 30
    for episode in report.episodes:
        start = data.pose_index[pose_key(*episode.start)]
        goal = data.goal_mask_for_instances(
            np.array([data.instance_ids.index(i) for i in episode.target_ids])
        )
        assert episode.optimal_length == data.distances_to(goal)[start] + 1 >= 1
    for _, reason in report.skipped:
        assert reason.split(":")[0] in {
            "target not reachable from the start",
            "start pose not reachable",
            "no object of that type nearby",
        }


def test_the_built_scene_decides_starts_and_unseeable_targets(floorplan425):
    data = floorplan425
    toilet = next(i for i in data.instance_ids if i.startswith("Toilet|"))
    goal = data.goal_mask_for_instances(np.array([data.instance_ids.index(toilet)]))
    # A position that does not see the toilet: cut it off (every MoveAhead from it fails).
    positions = sorted({(float(x), float(z)) for x, z in zip(data.x, data.z, strict=True)})
    at = {p: np.flatnonzero((data.x == p[0]) & (data.z == p[1])) for p in positions}
    cut = next(p for p in positions if not goal[at[p]].any() and len(at[p]) == 16)
    successors = data.successors.copy()
    successors[at[cut], 0] = at[cut]
    island = dataclasses.replace(data, successors=successors, _distance_cache={})
    start = (*cut, 90, 0)
    published = RawEpisode(0, "FloorPlan425", "Toilet", (toilet,), start)
    report = map_episodes([published], scene_data=lambda name: island)
    # The nearest pose with the same yaw and horizon from which the toilet can be reached.
    (episode,) = report.episodes
    assert episode.start != start and episode.start[2:] == (90, 0)
    assert 0 < np.hypot(episode.start[0] - cut[0], episode.start[1] - cut[1]) <= 0.36
    distance = island.distances_to(goal)[island.pose_index[pose_key(*episode.start)]]
    assert episode.optimal_length == distance + 1 >= 1
    assert (report.snapped_starts, report.exact_episodes, report.exact_ids) == (1, 0, 1)
    # Where no other pose is within reach, the episode is listed as unreachable.
    report = map_episodes([published], scene_data=lambda name: island, max_start_distance=0.1)
    assert dict(report.skipped)[0].startswith(f"target not reachable from the start: ['{toilet}']")
    # A start cut off with the toilet in sight moves to the connected part (the published versions'
    # pose graphs had no islands).
    seeing = next(p for p in positions if goal[at[p]].any() and len(at[p]) == 16)
    successors = data.successors.copy()
    successors[at[seeing], 0] = at[seeing]
    island = dataclasses.replace(data, successors=successors, _distance_cache={})
    on_island = RawEpisode(2, "FloorPlan425", "Toilet", (toilet,), (*seeing, 90, 0))
    (episode,) = map_episodes([on_island], scene_data=lambda name: island).episodes
    assert island.usable_poses[island.pose_index[pose_key(*episode.start)]]
    assert not island.usable_poses[at[seeing]].any() and episode.start[:2] != seeing
    # On the unmodified scene the published start stands: the published episode itself.
    report = map_episodes([published], scene_data=lambda name: data)
    assert report.episodes[0].start == start and report.exact_episodes == 1
    # Targets no pose sees, and why: inside a closed cabinet, in no frame, or in view only too far.
    spray, window = "SprayBottle|-01.38|+00.06|+02.77", "Window|-00.73|+01.67|-00.01"
    unseen = [
        RawEpisode(1, "FloorPlan425", "SprayBottle", (spray,), start),
        RawEpisode(2, "FloorPlan425", "Window", (window,), start),
    ]
    hidden_toilet = data.view_visible & (data.view_instance != data.instance_ids.index(toilet))
    far = dataclasses.replace(data, view_visible=hidden_toilet, _distance_cache={})
    why = "target visible from no pose: ['{}'] in FloorPlan425, {}"
    assert map_episodes(unseen, scene_data=lambda n: data).skipped == [
        (1, why.format(spray, "inside a closed receptacle")),
        (2, why.format(window, "in no pose's view (behind the simulator's walls or furniture)")),
    ]
    assert map_episodes([published], scene_data=lambda n: far).skipped == [
        (0, why.format(toilet, "in view only farther than the success distance"))
    ]


def test_cli_import_then_export(sample, floorplan425, tmp_path, monkeypatch, capsys):
    import argparse

    from mapless.cli import interop
    from mapless.episodes import evalsets
    from mapless.sim.library import SceneLibrary

    entries = [e for e in pickle.loads(sample.read_bytes()) if e["scene"] == "FloorPlan425"][:20]
    entries.append(
        {
            "scene": "FloorPlan9999",
            "goal_object_type": "Sink",
            "task_data": ["Sink|+0|+0|+0"],
            "state": "0.00|0.00|0|0",
            "glove_embedding": None,
        }
    )
    small = tmp_path / "bathroom_small.pkl"
    small.write_bytes(pickle.dumps(entries))
    data = floorplan425
    monkeypatch.setattr(
        SceneLibrary, "builtin", classmethod(lambda cls, config=None, cache_dir=None: cls(lambda n: data))
    )
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "imported.json.gz"
    args = parser.parse_args(["interop", "episodes-import", str(small), "--out", str(out), "--show-skipped"])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    assert "episodes mapped" in printed and "#20: unknown scene" in printed
    episodes, header = evalsets.load(out)
    assert header["split"] == "val" and 0 < len(episodes) <= 20
    assert all(e.optimal_length >= 1 and e.target_ids for e in episodes)
    pkl = tmp_path / "bathroom_savn.pkl"
    args = parser.parse_args(["interop", "episodes-export", str(out), "--format", "savn", "--out", str(pkl)])
    assert args.func(args) == 0
    back, bad = read_episode_file(pkl)
    assert not bad and len(back) == len(episodes)
    assert [b.target_ids for b in back] == [e.target_ids for e in episodes]
    assert back[0].embedding.shape == (300,)


def test_cli_reports_several_files_per_cause(sample, floorplan425, tmp_path, monkeypatch, capsys):
    import argparse

    from mapless.cli import interop
    from mapless.episodes import evalsets
    from mapless.sim.library import SceneLibrary

    entries = [e for e in pickle.loads(sample.read_bytes()) if e["scene"] == "FloorPlan425"]
    first, second = tmp_path / "first.pkl", tmp_path / "second.pkl"
    first.write_bytes(pickle.dumps(entries[:6]))
    second.write_bytes(pickle.dumps([*entries[6:9], {**entries[0], "scene": "FloorPlan9999"}]))
    monkeypatch.setattr(
        SceneLibrary,
        "builtin",
        classmethod(lambda cls, config=None, cache_dir=None: cls(lambda n: floorplan425)),
    )
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "both.json.gz"
    args = parser.parse_args(["interop", "episodes-import", str(first), str(second), "--out", str(out)])
    assert args.func(args) == 0
    table = capsys.readouterr().out.split("| set |", 1)[1].splitlines()
    assert table[0].endswith("| skipped: unknown scene |")
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table[2:4]}
    assert rows["first.pkl"].startswith("| first.pkl | 6 | 6 (100.0%) |") and rows["first.pkl"].endswith(
        "| 0 |"
    )
    assert rows["second.pkl"].startswith("| second.pkl | 4 | 3 (75.0%) |") and rows["second.pkl"].endswith(
        "| 1 |"
    )
    episodes, header = evalsets.load(out)
    assert len(episodes) == 9 and header["split"] == "val"
    assert {e.episode_id.split("/")[0] for e in episodes} == {"first", "second"}  # told apart by file
    # 'hoz22' names the shipped published files, val and test of each room type.
    files = interop._episode_files("hoz22")
    assert [f.name for f in files[:2]] == ["kitchen_val_22.pkl.gz", "kitchen_test_22.pkl.gz"]
    assert len(files) == 8 and all(f.is_file() for f in files)


def test_import_onto_an_offline_root_keeps_its_object_ids(sample, floorplan425, tmp_path, capsys):
    import argparse

    from mapless.cli import interop
    from mapless.episodes import evalsets
    from mapless.offline.writer import export_scene

    export_scene(floorplan425, tmp_path / "root", "savn")
    entries = [e for e in pickle.loads(sample.read_bytes()) if e["scene"] == "FloorPlan425"][:10]
    small = tmp_path / "bathroom_small.pkl"
    small.write_bytes(pickle.dumps(entries))
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "imported.json.gz"
    args = parser.parse_args(
        ["interop", "episodes-import", str(small), "--out", str(out), "--offline-dir", str(tmp_path / "root")]
    )
    assert args.func(args) == 0
    episodes, _ = evalsets.load(out)
    offline = offline_library(tmp_path / "root")["FloorPlan425"]
    assert episodes and all(set(e.target_ids) <= set(offline.instance_ids) for e in episodes)
    for e in episodes:  # the stored shortest paths are the offline root's
        goal = offline.goal_mask_for_instances(offline.goal_instances(e.target, e.target_ids))
        assert e.optimal_length == offline.distances_to(goal)[offline.pose_index[pose_key(*e.start)]] + 1


class _ObjectFieldDtype:
    """Pickles as a structured dtype with an object field whose state claims it holds no objects."""

    def __reduce__(self):
        return np.dtype, ("V8", False, True), (3, "|", None, ("a",), {"a": (np.dtype("O"), 0)}, 8, 1, 0)


class _ArrayFromBytes:
    """Pickles as numpy's array reconstruction of raw bytes with a given dtype."""

    def __init__(self, dtype, data: bytes, shape=(1,)):
        self.dtype, self.data, self.shape = dtype, data, shape

    def __reduce__(self):
        from numpy._core.multiarray import _reconstruct

        return _reconstruct, (np.ndarray, (0,), b"b"), (1, self.shape, self.dtype, False, self.data)


def _episode_file(tmp_path, embedding) -> Path:
    path = tmp_path / "crafted.pkl"
    entry = {"scene": "FloorPlan1", "goal_object_type": "Mug", "task_data": [], "state": "0.00|0.00|0|0"}
    path.write_bytes(pickle.dumps([{**entry, "glove_embedding": embedding}]))
    return path


@pytest.mark.parametrize(
    "embedding",
    [
        _ArrayFromBytes(_ObjectFieldDtype(), b"\x41" * 8),  # a pointer smuggled into an object field
        np.zeros(2, dtype=[("a", "f4"), ("b", "i4")]),  # any structured dtype
        np.array([1, "x"], dtype=object),  # object arrays
        _ArrayFromBytes(np.dtype("f8"), b"\x00" * 7, shape=(1,)),  # bytes that do not fill the shape
        _ArrayFromBytes(np.dtype("f8"), b"\x00" * 8, shape=(-1,)),  # a negative size
    ],
    ids=["object-field", "structured", "object-array", "short-data", "negative-shape"],
)
def test_crafted_arrays_are_refused_without_touching_memory(tmp_path, embedding):
    with pytest.raises(OfflineFormatError, match="not a readable episode pickle"):
        read_episode_file(_episode_file(tmp_path, embedding))


def test_plain_numeric_arrays_still_load_exactly(tmp_path):
    vector = np.arange(300, dtype=np.float32) / 7
    episodes, bad = read_episode_file(_episode_file(tmp_path, vector))
    assert not bad
    np.testing.assert_array_equal(episodes[0].embedding, vector.astype(np.float64))
    fortran = np.asfortranarray(np.arange(6, dtype=">i4").reshape(2, 3))
    episodes, _ = read_episode_file(_episode_file(tmp_path, fortran))
    np.testing.assert_array_equal(episodes[0].embedding, fortran)


def test_exported_task_data_lists_only_ids_of_the_visible_object_map(tmp_path, floorplan425, savn_module):
    seen = {floorplan425.instance_ids[i] for i in np.unique(floorplan425.visible_matrix_csr[1])}
    towels = [i for i in floorplan425.instance_ids if i.startswith("Towel|")]
    start = floorplan425.pose_tuple(0)
    named = Episode("FloorPlan425", "Towel", start, 5, (*towels, "Towel|+09.00|+00.00|+09.00"))
    every = Episode("FloorPlan425", "SoapBottle", start)  # task_data: every instance of the type
    glove = {"Towel": np.ones(300), "SoapBottle": np.ones(300)}
    path = tmp_path / "bathroom_test.pkl"
    write_episode_file([named, every], path, "mjolnir", embeddings=glove, visible_ids=lambda scene: seen)
    loaded = pickle.loads(path.read_bytes())
    assert loaded[0]["task_data"] == [t for t in towels if t in seen] and loaded[1]["task_data"]
    assert all(i in seen for entry in loaded for i in entry["task_data"])
    with pytest.raises(Exception, match="no pose sees any Towel"):
        write_episode_file([named], path, embeddings=glove, visible_ids=lambda scene: set())


def test_v1_names_stand_in_for_missing_vectors(tmp_path, savn_module):
    # SAVN's GloVe table has Lamp, not DeskLamp: the savn target set exports with it.
    episode = Episode("FloorPlan301", "DeskLamp", (0.0, 0.0, 0, 0), 3, ("DeskLamp|+00.00|+00.00|+00.00",))
    assert write_episode_file([episode], tmp_path / "x.pkl", embeddings={"Lamp": np.full(300, 2.0)}) == 1
    np.testing.assert_allclose(pickle.loads((tmp_path / "x.pkl").read_bytes())[0]["glove_embedding"], 2.0)


def test_one_file_per_room_type_as_the_references_read_them(
    tmp_path, floorplan425, monkeypatch, capsys, savn_module
):
    import argparse

    from mapless.cli import interop
    from mapless.episodes import evalsets
    from mapless.sim.library import SceneLibrary

    monkeypatch.setattr(
        SceneLibrary,
        "builtin",
        classmethod(lambda cls, config=None, cache_dir=None: cls(lambda n: floorplan425)),
    )
    made = [
        Episode("FloorPlan425", "SoapBar", floorplan425.pose_tuple(0), episode_id=f"val/bathroom/{i:03d}")
        for i in range(3)
    ]
    calls = []
    monkeypatch.setattr(
        evalsets, "make_eval_set", lambda library, split, target_set: calls.append(target_set) or made
    )
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(
        ["interop", "episodes-export", "val", "--target-set", "savn", "--out", str(tmp_path)]
    )
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    assert (
        calls == ["savn"] and "making it" in printed and "fewer than the references' --num_ep 250" in printed
    )
    assert sorted(p.name for p in tmp_path.glob("*.pkl")) == ["bathroom_val.pkl"]
    back, bad = read_episode_file(tmp_path / "bathroom_val.pkl")
    assert not bad and len(back) == 3
    # The built-in test set: one file per room type, 250 episodes each.
    from mapless.offline.episode_writer import write_room_files

    episodes = evalsets.load(evalsets.builtin_path("test"))[0]
    files = write_room_files(
        episodes, tmp_path / "test", "test", embeddings={e.target: np.ones(300) for e in episodes}
    )
    assert [p.name for p in files.values()] == [
        f"{r}_test.pkl" for r in ("kitchen", "living_room", "bedroom", "bathroom")
    ]
    assert all(len(pickle.loads(p.read_bytes())) == 250 for p in files.values())
