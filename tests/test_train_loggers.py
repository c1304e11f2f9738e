"""Where a training run's records go: TensorBoard by default, Weights & Biases beside it with
``logger: [tensorboard, wandb]`` (the wandb extra; here in wandb's offline mode, no account), and a
clear error, before any training, where wandb is asked for but not installed."""

from __future__ import annotations

import json
import sys

import pytest
from train_fixtures import fixture_library as training_scenes

from mapless.config import ConfigError, apply_overrides, from_dict, to_dict
from mapless.experiments import load_experiment, run_dir_for, train_config
from mapless.train.config import TrainConfig
from mapless.train.run import train


def _config(*overrides: str) -> TrainConfig:
    base = {
        "model": {"name": "a3c", "hidden_size": 16, "dropout": 0.0},
        "env": {"scenes": "FloorPlan1,FloorPlan2", "max_steps": 8},
        "a3c": {"batch_size": 4},
        "episodes": 8,
        "checkpoint_every": 4,
        "log_every": 4,
        "threads": 1,
        "progress": False,
    }
    return from_dict(TrainConfig, apply_overrides(base, list(overrides)))


def test_tensorboard_is_the_default_logger(tmp_path) -> None:
    assert _config().logger == ("tensorboard",)
    train(_config(), tmp_path / "run", library_factory=training_scenes)
    assert list((tmp_path / "run").glob("events.out.tfevents.*"))
    assert not (tmp_path / "run" / "wandb").exists()


@pytest.mark.slow
def test_a_wandb_run_is_written_in_offline_mode(tmp_path, monkeypatch) -> None:
    wandb = pytest.importorskip("wandb", reason="the wandb extra (in the dev extra) is not installed")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "wandb_home"))
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = tmp_path / "run"
    train(_config("logger=[tensorboard, wandb]"), run, library_factory=training_scenes)
    wandb.teardown()  # waits for wandb's service to write what it was sent, as the process's exit does
    assert list(run.glob("events.out.tfevents.*"))  # TensorBoard still writes beside it
    (offline,) = (run / "wandb").glob("offline-run-*")
    (records,) = offline.glob("run-*.wandb")
    assert offline.name.endswith(f"-{run.name}") and records.stat().st_size > 0
    # wandb's offline record file (a binary log) holds every key metrics.jsonl has.
    logged = records.read_bytes()
    keys = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1]).keys() - {
        "episodes",
        "frames",
        "time",
    }
    assert {"charts/success", "losses/total", "perf/frames"} <= keys
    assert all(key.encode() in logged for key in keys)


def test_wandb_asked_for_but_not_installed_stops_before_training(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "wandb", None)  # import wandb raises ImportError
    with pytest.raises(ConfigError, match=r"logger': wandb is not installed; pip install .*\[wandb\]"):
        train(_config("logger=[wandb]"), tmp_path / "run", library_factory=training_scenes)
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


def test_logger_names_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"'logger': must list tensorboard and/or wandb.*'mlflow'"):
        _config("logger=[mlflow]")
    with pytest.raises(ConfigError, match="each at most once"):
        _config("logger=[wandb, wandb]")
    assert _config("logger=[]").logger == ()


def test_the_logger_leaves_a_reproduce_runs_folder_alone() -> None:
    """Runs are found again by a hash of their training config: where its records go changes none."""
    experiment = load_experiment("table1", "smoke")
    plain = train_config(experiment, "a3c", 1)
    logged = from_dict(TrainConfig, {**to_dict(plain), "logger": ["tensorboard", "wandb"]})
    assert run_dir_for(experiment, plain, "all") == run_dir_for(experiment, logged, "all")
