"""Malformed user files and unusable folders end in one clear line (``mapless: error: ...``, exit 2)
or are handled, never in a traceback. Every bad file is made here."""

from __future__ import annotations

import errno
import json
import pickle
import re
import shutil

import pytest
from scene_fixtures import grid_scene

from mapless.cli import main
from mapless.config import ConfigError, load_config
from mapless.configs import configs_dir
from mapless.episodes import evalsets
from mapless.offline import OfflineFormatError, export_scene, load_offline_scene, read_episode_file
from mapless.sim import cache
from mapless.sim.config import SimConfig
from mapless.train.config import TrainConfig

SCENE = "FloorPlan425"  # the smallest bathroom
FAST = SimConfig(ray_resolution=14)
FAST_ARGS = ["--sim", "ray_resolution=14"]


def error_of(argv: list[str], capsys) -> str:
    """The one-line error of a command that must fail cleanly (exit 2, no traceback)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.count("mapless: error: ") == 1, err
    # the one line (a progress bar may precede it on the same terminal line)
    return err[err.index("mapless: error: ") :].splitlines()[0]


# ----------------------------------------------------------------------------------------- configs


def test_a_config_that_is_not_utf8_is_a_config_error(tmp_path, capsys):
    path = tmp_path / "latin1.yaml"
    path.write_bytes("seed: 1\n# r\xe9sum\xe9\n".encode("latin-1"))
    assert "not UTF-8" in error_of(["train", str(path)], capsys)


def test_an_unknown_nested_key_is_quoted_whole(tmp_path):
    path = tmp_path / "typo.yaml"
    path.write_text("a3c:\n  learning_rate: 0.1\n")
    with pytest.raises(ConfigError, match=r"unknown config key 'a3c\.learning_rate'; valid keys here: "):
        load_config(TrainConfig, path)
    path.write_text("a3c:\n  1: 0.1\n  lr_: 0.2\n")  # keys of mixed types are still sorted
    with pytest.raises(ConfigError, match=r"unknown config key 'a3c\.1'"):
        load_config(TrainConfig, path)


def test_a_value_of_an_optional_key_says_why_it_is_refused(tmp_path):
    path = tmp_path / "cache.yaml"
    path.write_text("env:\n  cache_dir: [1]\n")
    with pytest.raises(
        ConfigError, match=r"'env\.cache_dir': \[1\] matches none of .* \(expected a string, got \[1\]\)"
    ):
        load_config(TrainConfig, path)


def test_a_missing_offline_root_is_named_and_leaves_no_run_folder(tmp_path, capsys):
    config = tmp_path / "offline.yaml"
    config.write_text("model:\n  name: mlp\nenv:\n  scenes: FloorPlan1\nepisodes: 16\na3c: {batch_size: 4}\n")
    runs = tmp_path / "runs"
    argv = [
        "train",
        str(config),
        "--set",
        f"env.offline_dir={tmp_path / 'nowhere'}",
        "--runs-root",
        str(runs),
    ]
    err = error_of(argv, capsys)
    assert "no such offline data root" in err and "Valid choices" not in err
    assert not runs.exists() or not list(runs.iterdir())  # no folder holding only config.yaml


def test_an_empty_list_of_choices_says_none():
    from mapless.errors import UnknownNameError

    assert str(UnknownNameError("scene folder in /x", "FloorPlan1", [])).endswith("Valid choices: none")


def test_an_empty_checkpoint_gives_a_reason(tmp_path):
    from mapless.checkpoint import CheckpointError, load_file

    empty = tmp_path / "checkpoint.pt"
    empty.write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"cannot read checkpoint .*checkpoint\.pt: \S"):
        load_file(empty)


def test_counts_below_one_are_refused_by_the_parser(capsys):
    for argv in (["eval", "random", "--per-room", "0"], ["reproduce", "table1", "--seeds", "0"]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2 and "must be >= 1, got 0" in capsys.readouterr().err


# ---------------------------------------------------------------------------------- episode files


def _episode_json(tmp_path, payload) -> str:
    path = tmp_path / "episodes.json"
    path.write_text(json.dumps(payload))
    return str(path)


def _header(episodes: list) -> dict:
    return {
        "format": evalsets.FORMAT,
        "split": "val",
        "scenes": "x21-x25",
        "target_set": "mjolnir22",
        "seed": 0,
        "sim_fingerprint": "0" * 16,
        "episodes": episodes,
    }


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        ([1, 2], "not a mapless-episodes/1 file"),
        (_header([{"scene": "FloorPlan21", "target": "Apple"}]), "episode 0: episode has no start"),
        (
            _header([{"scene": "FloorPlan21", "target": "Apple", "start": [0, 0, "a", 0]}]),
            "episode 0: .*start",
        ),
        (_header([{"scene": 21, "target": "Apple", "start": [0, 0, 0, 0]}]), "scene 21 is not a string"),
        ({**_header([]), "episodes": {"a": 1}}, "'episodes' is missing or not a list"),
    ],
    ids=["top-level-list", "no-start", "bad-start", "scene-number", "episodes-mapping"],
)
def test_malformed_episode_json_is_one_error(tmp_path, capsys, payload, message):
    err = error_of(["episodes", "show", _episode_json(tmp_path, payload)], capsys)
    assert "episodes.json" in err
    assert re.search(message, err), err


def test_an_episode_pickle_with_bad_task_data_skips_the_entry_with_a_reason(tmp_path, capsys):
    path = tmp_path / "task5.pkl"
    entry = {"scene": "FloorPlan1", "goal_object_type": "Mug", "state": "0.00|0.00|0|0"}
    path.write_bytes(pickle.dumps([{**entry, "task_data": 5}, {**entry, "task_data": [b"id"]}]))
    episodes, bad = read_episode_file(path)
    assert not episodes and [i for i, _ in bad] == [0, 1]
    assert all("task_data is not an object id or a list of object ids" in reason for _, reason in bad)
    assert main(["interop", "episodes-import", str(path)]) == 0
    assert "0 of 2 episodes mapped, 2 skipped" in capsys.readouterr().out


def test_an_episode_pickle_with_a_nan_start_skips_the_entry_with_a_reason(tmp_path, capsys):
    """A dict state with x = z = NaN was mapped to an arbitrary start (issue 45, point 9)."""
    path = tmp_path / "nan.pkl"
    entry = {"scene": "FloorPlan1", "goal_object_type": "Mug", "task_data": ["Mug|+1.00|+0.90|+1.00"]}
    nan, inf = float("nan"), float("inf")
    states = [
        {"x": nan, "y": 0.9, "z": nan, "rotation": 90, "horizon": 0},
        {"x": 1.0, "y": 0.9, "z": inf, "rotation": 90, "horizon": 0},
        "nan|nan|90|0",
    ]
    path.write_bytes(pickle.dumps([{**entry, "state": state} for state in states]))
    episodes, bad = read_episode_file(path)
    assert not episodes and [i for i, _ in bad] == [0, 1, 2]
    assert all("no finite x, z" in reason or "is not 'x|z|rotation|horizon'" in reason for _, reason in bad)
    assert main(["interop", "episodes-import", str(path)]) == 0
    out = capsys.readouterr().out
    assert "0 of 3 episodes mapped" in out and "3 skipped" in out


def test_an_arrangement_file_of_a_few_bytes_cannot_claim_gigabytes(tmp_path, capsys):
    """Nine bytes made the arrangement reader die with a MemoryError (issue 45, point 16)."""
    path = tmp_path / "a.pkl"
    path.write_bytes(b"\x80\x02}r\xff\xff\xff\xff.")  # a memo index of 2**32: a 64 GiB memo table
    err = error_of(["scenes", "variants", str(path)], capsys)
    assert f"{path}: not an arrangement file in the rearrangement dataset's format" in err


# ------------------------------------------------------------------------------ offline folders


@pytest.fixture(scope="module")
def scene():
    return grid_scene()


@pytest.mark.parametrize(
    "boxes",
    [["a", 1, 2, 3], [[1, 2, 3, 4], [1, 2]], [1, 2, 3, None], [1, 2, 3, True], [1, 2, 3, float("nan")]],
    ids=["text", "ragged", "null", "bool", "nan"],
)
def test_bad_boxes_name_the_file(scene, tmp_path, capsys, boxes):
    folder = export_scene(scene, tmp_path, "mjolnir")
    path = folder / "objects_bb.json"
    data = json.loads(path.read_text())
    pose = next(iter(data))
    data[pose] = {"Mug": boxes}
    path.write_text(json.dumps(data))
    err = error_of(["interop", "check", str(folder)], capsys)
    assert "objects_bb.json" in err and "boxes must be a flat list of finite numbers" in err


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("feature_channels", "many", "feature_channels 'many' is not a count"),
        ("feature_channels", 100000, "feature_channels 100000 exceeds the 512 channels"),
        ("features_dtype", "object", "features_dtype 'object' is not one of"),
        ("features_dtype", 7, "features_dtype 7 is not one of"),
        ("feature_scale", 0, "feature_scale 0 is not a positive number"),
        ("alias_types", 3, "alias_types 3 is not a list of types"),
    ],
)
def test_a_bad_side_file_names_the_file(scene, tmp_path, capsys, field, value, message):
    folder = export_scene(scene, tmp_path, "mjolnir")
    side = folder / "mapless.json"
    side.write_text(json.dumps({**json.loads(side.read_text()), field: value}))
    with pytest.raises(OfflineFormatError, match=r"mapless\.json") as error:
        load_offline_scene(folder)
    assert message in str(error.value)
    assert message in error_of(["interop", "check", str(folder)], capsys)


# ----------------------------------------------------------------------------------- scene cache


def test_cache_dir_and_the_variable_name_one_cache_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPLESS_CACHE", str(tmp_path))
    by_variable = cache.cache_path(SCENE, FAST)
    assert by_variable == cache.cache_path(SCENE, FAST, tmp_path)
    assert by_variable.parent.parent == tmp_path / "scenes"
    monkeypatch.setenv("MAPLESS_CACHE", "")  # set but empty: the default, not the working directory
    assert cache.cache_path(SCENE, FAST).is_absolute()


def test_an_unwritable_cache_keeps_the_built_scene_in_memory(tmp_path, monkeypatch):
    def read_only(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied", str(dst))

    monkeypatch.setattr("mapless.files.os.replace", read_only)
    with pytest.warns(
        UserWarning, match="cannot write the scene cache file .*Permission denied.*kept in memory"
    ):
        data = cache.load_or_build(SCENE, FAST, tmp_path)
    assert data.scene == SCENE and data.n_poses > 0
    assert not cache.cache_path(SCENE, FAST, tmp_path).exists()


def test_scenes_build_refuses_an_unwritable_cache_before_building(tmp_path, monkeypatch, capsys):
    root = tmp_path / "root"
    root.write_text("a file where the cache root should be")
    monkeypatch.setattr(cache, "build_scene_data", lambda *a: pytest.fail("built before checking"))
    err = error_of(["scenes", "build", SCENE, "--cache-dir", str(root), "--workers", "1", *FAST_ARGS], capsys)
    assert "is not writable" in err and "--cache-dir" in err
    # Training and evaluation only prepare the cache: they go on, building in memory when used.
    with pytest.warns(UserWarning, match="is not writable"):
        assert cache.build_many([SCENE], FAST, root, missing_only=True, progress=False) == []


def test_a_folder_where_the_cache_file_should_be(tmp_path, capsys):
    path = cache.cache_path(SCENE, FAST, tmp_path)
    path.mkdir(parents=True)
    with pytest.warns(UserWarning, match="cannot write the scene cache file .*kept in memory"):
        assert cache.load_or_build(SCENE, FAST, tmp_path).scene == SCENE
    err = error_of(
        ["scenes", "build", SCENE, "--cache-dir", str(tmp_path), "--workers", "1", *FAST_ARGS], capsys
    )
    assert "cannot write the scene cache file" in err and str(path) in err


def test_the_cache_folder_deleted_during_a_build(tmp_path, monkeypatch):
    build = cache.build_scene_data
    folder = cache.cache_path(SCENE, FAST, tmp_path).parent

    def build_then_delete(*args):
        data = build(*args)
        shutil.rmtree(tmp_path / "scenes")  # e.g. a user clearing the cache meanwhile
        return data

    folder.mkdir(parents=True)
    monkeypatch.setattr(cache, "build_scene_data", build_then_delete)
    data = cache.load_or_build(SCENE, FAST, tmp_path)
    monkeypatch.undo()
    assert cache.load(folder / f"{SCENE}.npz", FAST).n_poses == data.n_poses  # written all the same


def test_a_negative_seed_is_a_config_error_naming_the_key(tmp_path, capsys):
    """numpy's SeedSequence refuses it with a bare traceback (issue 45, points 1 and 14)."""
    smoke = str(configs_dir() / "train_smoke.yaml")
    runs = tmp_path / "runs"
    err = error_of(["train", smoke, "--set", "seed=-1", "--runs-root", str(runs)], capsys)
    assert "config key 'seed': must be >= 0" in err and not runs.exists()
    err = error_of(["reproduce", "table1", "--set", "eval.seed=-1", "--reports", str(tmp_path)], capsys)
    assert "config key 'eval.seed': must be >= 0" in err


def test_a_model_with_nan_weights_is_refused_before_evaluation(tmp_path, capsys, monkeypatch):
    """A valid digest, NaN weights: evaluated with SR 0 and exit 0 before (issue 45, points 3 and 12)."""
    import torch
    from train_fixtures import tiny_config

    from mapless import checkpoint as ckpt
    from mapless.models import build_model
    from mapless.train.run import resume_config

    config = tiny_config("a3c")
    weights = {k: torch.full_like(v, float("nan")) for k, v in build_model(config.model).state_dict().items()}
    model = tmp_path / "model.pt"
    ckpt.atomic_save(ckpt.model_payload(weights, config, {"episodes": 4, "frames": 20}), model)
    monkeypatch.setattr("mapless.evaluate.selection.evaluate", lambda *a, **k: pytest.fail("evaluated"))
    err = error_of(["eval", str(model), "--per-room", "1", "--out", str(tmp_path / "eval")], capsys)
    assert f"{model} holds a diverged model" in err and "NaN or infinite" in err
    assert not (tmp_path / "eval").exists()
    run = tmp_path / "run"  # nor is such a checkpoint resumed
    state = {**ckpt.model_payload(weights, config, {}), "kind": "checkpoint", "optimizer": {}, "rng": []}
    ckpt.atomic_save(state, run / ckpt.CHECKPOINT_FILE)
    with pytest.raises(ckpt.CheckpointError, match="holds a diverged model"):
        resume_config(run)


def test_episodes_make_checks_every_split_before_it_writes_one(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(evalsets, "make_eval_set", lambda *a, **k: pytest.fail("made a set"))
    err = error_of(["episodes", "make", "--splits", "val,tset", "--out", str(tmp_path)], capsys)
    assert "no evaluation split 'tset'" in err
    assert not list(tmp_path.iterdir())


def test_eval_options_that_do_not_apply_are_refused_before_the_episodes_load(capsys, monkeypatch):
    monkeypatch.setattr("mapless.evaluate.episode_sets.load_episodes", lambda *a, **k: pytest.fail("loaded"))
    err = error_of(["eval", "random", "--select"], capsys)
    assert "--select needs a run folder" in err
    for option in (["--no-adapt"], ["--inner-lr", "0.1"]):
        err = error_of(["eval", "random", *option], capsys)
        assert "--no-adapt and --inner-lr are for a trained adaptive model" in err


def test_an_unwritable_output_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    """eval --out, train --run-dir and scenes show --out ended in a bare traceback, eval's after the
    whole evaluation (issue 45, point 13): each is checked first, naming the path."""
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    monkeypatch.setattr("mapless.evaluate.runner.evaluate", lambda *a, **k: pytest.fail("evaluated"))
    err = error_of(["eval", "random", "--per-room", "1", "--out", str(blocker / "eval")], capsys)
    assert f"--out {blocker / 'eval'}: {blocker} is not a folder; nothing was evaluated" in err
    (tmp_path / "out" / "test.json").mkdir(parents=True)  # eval's default split is test
    err = error_of(["eval", "random", "--per-room", "1", "--out", str(tmp_path / "out")], capsys)
    assert f"{tmp_path / 'out' / 'test.json'} is a folder" in err

    smoke = str(configs_dir() / "train_smoke.yaml")
    err = error_of(["train", smoke, "--run-dir", str(blocker)], capsys)
    assert f"cannot write the run folder {blocker}: {blocker} is not a folder" in err
    err = error_of(["scenes", "show", SCENE, "--out", str(blocker / "scene.png")], capsys)
    assert f"--out {blocker / 'scene.png'}: {blocker} is not a folder" in err
    # reproduce wrote its report last, after hours of training: its folder is checked first too.
    monkeypatch.setattr(
        "mapless.experiments.launch.LocalLauncher.train", lambda *a, **k: pytest.fail("trained")
    )
    err = error_of(["reproduce", "table1", "--budget", "smoke", "--reports", str(blocker)], capsys)
    assert f"cannot write the report in {blocker / 'table1'}: {blocker} is not a folder" in err

    def denied(*args, **kwargs):  # what a user other than root meets in a folder of root's
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr("mapless.files.tempfile.TemporaryFile", denied)
    err = error_of(["eval", "random", "--per-room", "1", "--out", str(tmp_path / "denied")], capsys)
    assert f"cannot write in {tmp_path}: Permission denied" in err
    err = error_of(["train", smoke, "--run-dir", str(tmp_path / "run")], capsys)
    assert "cannot write the run folder" in err and "Permission denied" in err
    assert not (tmp_path / "denied").exists() and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "override",
    [
        "model.hidden_size=-1",
        "model.hidden_size=0",
        "model.fusion_channels=0",
        "model.feature_channels=0",
        "model.interaction_steps=0",
        "model.gcn_hidden=0",
        "model.max_inner_updates=-1",
        "model.dropout=1",
        "model.dropout=nan",
    ],
)
def test_an_impossible_model_size_is_a_config_error(override, tmp_path, capsys):
    """A RuntimeError traceback from torch, or (0) a model without units that trained (issue 45, 15)."""
    smoke = str(configs_dir() / "train_smoke.yaml")
    for model in ("a3c", "savn", "mjolnir_o", "cvmeta"):
        argv = ["train", smoke, "--set", f"model.name={model}", "--set", override]
        err = error_of([*argv, "--runs-root", str(tmp_path)], capsys)
        assert f"config key '{override.split('=')[0]}': must " in err
    assert not list(tmp_path.iterdir())


def test_an_experiment_of_no_model_is_a_config_error(tmp_path, capsys):
    """It trained nothing and wrote an empty Table 1, exit 0 (issue 45, point 18)."""
    argv = ["reproduce", "table1", "--budget", "smoke", "--set", "models=[]", "--reports", str(tmp_path)]
    assert "config key 'models': the list is empty" in error_of(argv, capsys)
    assert not list(tmp_path.iterdir())
