"""The training target sets and the evaluation sets that follow them: the ``hoz22`` target set is
the published HOZ files' classes and trains; under the reference protocol the sets an experiment
selects and reports on are the training target set's; an experiment refuses episodes of targets
its runs never trained for, and ``mapless eval`` says so."""

from __future__ import annotations

import collections
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from train_fixtures import tiny_config

from mapless import checkpoint as ckpt
from mapless.cli import main
from mapless.episodes import evalsets
from mapless.episodes.sampler import TrainingSampler
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import first_per_room
from mapless.experiments import load_experiment
from mapless.experiments.evaluator import Evaluator
from mapless.knowledge import parent_lists, parent_weights
from mapless.knowledge.glove import glove_vector
from mapless.knowledge.graph import hierarchical_adjacency, normalize_adjacency
from mapless.offline.episodes import read_episode_file
from mapless.scenes.catalogue import ROOM_TYPES, scene_names
from mapless.scenes.categories import (
    CATEGORY_SETS,
    HOZ22_TARGETS,
    TARGET_SETS,
    all_targets,
    category_set,
)
from mapless.scenes.layout import load_scene
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import pose_key
from mapless.train.config import EnvConfig, stored_train_config
from mapless.train.run import train

pytestmark = pytest.mark.usefixtures("single_torch_thread")


def test_hoz22_is_the_union_of_the_published_files_goal_types_per_room_type():
    for room in ROOM_TYPES:
        goals = {
            e.target_type
            for split in evalsets.PUBLISHED["hoz22"][1]
            for e in read_episode_file(evalsets.published_path("hoz22", split, room))[0]
        }
        assert goals == set(HOZ22_TARGETS[room])
    assert len(all_targets("hoz22")) == 22
    assert len(set(all_targets("hoz22")) & set(all_targets("mjolnir22"))) == 7


@pytest.mark.parametrize("target_set", sorted(TARGET_SETS))
def test_every_target_is_a_category_with_a_glove_vector(target_set):
    # The models read a target's GloVe vector and its context row (target_index; -1 would give a
    # zero row), and the graph models' nodes are the categories: every target is one of each set.
    for name in CATEGORY_SETS:
        categories = category_set(name)
        for target in all_targets(target_set):
            assert target in categories.type_to_index, (name, target)
            assert glove_vector(target, name).shape == (300,)


def test_hoz22_targets_occur_in_the_training_floor_plans_of_their_room_type():
    for room, targets in HOZ22_TARGETS.items():
        present = set().union(
            *({o.type for o in load_scene(s).objects} for s in scene_names("train", (room,)))
        )
        assert set(targets) <= present, room


def test_hoz22_targets_add_their_parent_edges_to_hoz22_runs_graphs_only():
    for name in CATEGORY_SETS:
        lists = parent_lists(name)
        for room, targets in HOZ22_TARGETS.items():
            assert set(targets) <= set(lists[room]), (name, room)
    # The parent reward pays for a hoz22-only target (Pan's parents in kitchens include StoveBurner) ...
    names = category_set().names
    pan, burner = names.index("Pan"), names.index("StoveBurner")
    assert parent_weights("kitchen", "Pan")[burner] > 0
    # ... and a hoz22 run's graph links them, while every other run keeps the graph it always had:
    # 911 non-zeros (docs/guide/models.md), Pan and StoveBurner unlinked by VG's caption counts.
    shared = hierarchical_adjacency() > 0
    assert int(shared.sum()) == 911 and not shared[pan, burner]
    assert (hierarchical_adjacency(target_set="mjolnir22") == hierarchical_adjacency()).all()
    hoz = hierarchical_adjacency(target_set="hoz22") > 0
    assert hoz[pan, burner] and hoz[burner, pan] and int(hoz.sum()) == 947
    # Exactly the edges of the 21 (room type, target) pairs that hoz22 adds to mjolnir22's and SAVN's
    # (Pan in kitchens, Book in living rooms, ...) are new.
    earlier = {(r, t) for s in ("mjolnir22", "savn") for r, ts in TARGET_SETS[s].items() for t in ts}
    new_pairs = {(r, t) for r, ts in HOZ22_TARGETS.items() for t in ts} - earlier
    assert len(new_pairs) == 21 and ("kitchen", "Pan") in new_pairs
    expected = shared.copy()
    for room, target in new_pairs:
        for entry in parent_lists()[room][target]:
            i, j = names.index(target), names.index(entry["parent"])
            expected[i, j] = expected[j, i] = True
    assert (hoz == expected).all()


def test_a_training_run_on_hoz22_starts_from_the_hoz22_graph():
    from mapless.train.builders import new_model

    hoz = new_model(tiny_config("cvmeta", "env.target_set=hoz22")).A.detach().numpy()
    assert np.array_equal(hoz, normalize_adjacency(hierarchical_adjacency(target_set="hoz22")))
    default = new_model(tiny_config("cvmeta")).A.detach().numpy()
    assert np.array_equal(default, normalize_adjacency(hierarchical_adjacency()))
    assert not np.array_equal(default, hoz)


# ---------------------------------------------------------------- the sets an experiment reads


def _reference(*overrides: str):
    return load_experiment(
        "table1", "smoke", overrides=["eval.protocol=reference", "eval.per_room=3", *overrides]
    )


@pytest.mark.parametrize("target_set", ["mjolnir22", "hoz22", None])
def test_the_reference_protocol_reads_the_training_target_sets_sets(target_set):
    # hoz22 (the protocol's default, None): the published HOZ episodes; mjolnir22: the sampled sets.
    told = [f"train.env.target_set={target_set}"] if target_set else []
    ev = Evaluator(_reference(*told), log=print)
    target_set = target_set or "hoz22"
    for split, episodes in (("ref_val", ev.select_episodes), ("ref_test", ev.report_episodes)):
        shipped, header = evalsets.load(evalsets.builtin_path(split, target_set))
        assert header["target_set"] == target_set
        assert episodes == first_per_room(shipped, 3) and len(episodes) == 12
        assert episodes[0].episode_id.startswith("hoz22_" if target_set == "hoz22" else split)
        assert not evalsets.untrained_targets(episodes, target_set)
    assert ev.protocol_label.endswith(f"the episodes of target set {target_set}")


def test_an_explicit_file_still_overrides_the_sets_when_its_targets_fit(tmp_path):
    shipped, header = evalsets.load(evalsets.builtin_path("ref_test"))
    last = shipped[-3:]  # bathroom episodes the first 3 per room type do not hold
    evalsets.save(tmp_path / "mine.json.gz", last, "ref_test", "mjolnir22", 0, header["sim_fingerprint"])
    mine = f"eval.report_file={tmp_path / 'mine.json.gz'}"
    ev = Evaluator(_reference(mine, "train.env.target_set=mjolnir22"), log=print)
    assert ev.report_episodes == last and ev.select_episodes == first_per_room(
        evalsets.load(evalsets.builtin_path("ref_val"))[0], 3
    )


def test_an_experiment_refuses_episodes_its_runs_never_trained_for(tmp_path, capsys):
    with pytest.raises(MaplessError, match=r"--set train.env.target_set=hoz22") as error:
        Evaluator(_reference("eval.report_file=ref_test_hoz22", "train.env.target_set=mjolnir22"), log=print)
    message = str(error.value)
    assert "the report episodes (ref_test_hoz22.json.gz) do not fit the a3c runs" in message
    assert "of 12 episodes have targets the run never trained for" in message and "bathroom: " in message
    # From the command line: refused before any run is trained or any folder made.
    runs, reports = tmp_path / "runs", tmp_path / "reports"
    argv = ["reproduce", "table1", "--budget", "smoke", "--protocol", "reference", "--reports", str(reports)]
    sets = ["--set", f"runs_dir={runs}", "--set", "eval.select_file=ref_val_mjolnir22"]
    assert main([*argv, *sets]) != 0  # the protocol's default runs (hoz22) on MJOLNIR's episodes
    error = capsys.readouterr().err
    assert "the selection episodes (ref_val_mjolnir22.json.gz) do not fit" in error
    assert "--set train.env.target_set=mjolnir22" in error
    assert not runs.exists() and not reports.exists()


def test_untrained_targets_counts_per_room_type_and_class():
    def episode(scene: str, target: str) -> Episode:
        return Episode(scene, target, (0.0, 0.0, 0, 0), 2)

    episodes = [
        episode("FloorPlan21", "Toaster"),
        episode("FloorPlan21", "Pan"),
        episode("FloorPlan421", "Sink"),
    ]
    episodes.append(episode("FloorPlan421", "Sink"))
    found = evalsets.untrained_targets(episodes, "mjolnir22")
    assert found == {"kitchen": {"Pan": 1}, "bathroom": {"Sink": 2}}
    assert evalsets.untrained_targets(episodes[1:], "hoz22") == {}
    line = evalsets.describe_untrained(found, len(episodes), "mjolnir22")
    assert line.startswith("3 of 4 episodes have targets the run never trained for") and "Sink 2" in line


def test_only_hoz22s_reference_splits_are_its_published_episodes():
    assert evalsets.is_published("ref_test", "hoz22") and not evalsets.is_published("test", "hoz22")
    assert not evalsets.is_published("ref_test", "mjolnir22")


# ------------------------------------------------------- a tiny hoz22 run, and `mapless eval` on it


def _drawn(library: SceneLibrary, target_set: str, n: int) -> list[Episode]:
    """``n`` training draws of ``target_set`` in FloorPlan401, with their optimal lengths."""
    sampler, rng, out = (
        TrainingSampler(library, ["FloorPlan401"], target_set, seed=0),
        np.random.default_rng(0),
        [],
    )
    for i in range(n):
        episode = sampler.sample(rng)
        data = library[episode.scene]
        distance = int(data.target_distances(episode.target)[data.pose_index[pose_key(*episode.start)]])
        out.append(dataclasses.replace(episode, optimal_length=distance + 1, episode_id=f"{target_set}/{i}"))
    return out


@pytest.mark.slow
def test_a_hoz22_run_trains_and_eval_flags_targets_it_never_trained_for(tmp_path, capsys):
    # One bathroom (built once into the session's test cache): hoz22's bathroom targets are
    # GarbageCan, LightSwitch and Sink, none of them a mjolnir22 target there.
    library = SceneLibrary.builtin()
    hoz = _drawn(library, "hoz22", 30)
    assert {e.target for e in hoz} == set(HOZ22_TARGETS["bathroom"])
    # cvmeta: a graph model that also trains with the parent reward of its targets.
    config = tiny_config("cvmeta", "env.scenes=FloorPlan401", "env.target_set=hoz22", "meta.first_order=true")
    run = tmp_path / "run"
    summary = train(config, run)
    assert summary["episodes"] == 8 and summary["frames"] > 0
    assert (
        stored_train_config(ckpt.load_file(run / ckpt.FINAL_MODEL_FILE)["config"]).env.target_set == "hoz22"
    )

    fp = fingerprint(SimConfig())
    own, other = tmp_path / "own.json.gz", tmp_path / "other.json.gz"
    evalsets.save(own, hoz[:3], "val", "hoz22", 0, fp)
    mjolnir = _drawn(library, "mjolnir22", 2)  # bathroom targets a hoz22 run never trained for
    evalsets.save(other, [hoz[0], *mjolnir], "val", "mjolnir22", 0, fp)
    argv = ["eval", str(run / ckpt.FINAL_MODEL_FILE), "--workers", "1", "--out", str(tmp_path / "eval")]
    assert main([*argv, "--episodes", str(own)]) == 0
    assert "never trained for" not in capsys.readouterr().err
    assert "untrained_targets" not in json.loads((tmp_path / "eval" / "own.json").read_text())
    assert main([*argv, "--episodes", str(other)]) == 0
    assert "warning: 2 of 3 episodes have targets the run never trained for" in capsys.readouterr().err
    record = json.loads((tmp_path / "eval" / "other.json").read_text())
    classes = dict(collections.Counter(e.target for e in mjolnir))
    assert record["untrained_targets"] == {
        "target_set": "hoz22",
        "episodes": 2,
        "of": 3,
        "classes": {"bathroom": classes},
    }
    assert "**Not the training targets**: 2 of 3 episodes" in (tmp_path / "eval" / "other.md").read_text()


def test_run_folder_names_keep_the_default_target_set():
    # The default stays mjolnir22, so no run folder moves (tests/data/run_folders.json pins them).
    assert EnvConfig().target_set == "mjolnir22"
    assert Path(evalsets.set_path("ref_test")).name == "ref_test_mjolnir22.json.gz"
