"""Bad inputs that ended in a traceback or were silently accepted: each is now a clear error (the
problem named, exit 2 from the command line, nothing written) or reported."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import gymnasium as gym
import pytest

import mapless
from mapless.cli import main as cli_main
from mapless.config import ConfigError
from mapless.errors import MaplessError
from mapless.experiments.config import read_experiment
from mapless.experiments.launch import SlurmLauncher, slurm_problem
from mapless.offline.episodes import RawEpisode, map_episodes
from mapless.scenes import load_scene
from mapless.sim.env import NavEnv
from mapless.train.recipes import with_recipe


def _recipe(tmp_path: Path, text: str) -> Path:
    (tmp_path / "r.yaml").write_text(text)
    return tmp_path


def test_a_recipe_naming_an_unknown_model_is_refused_with_a_suggestion(tmp_path):
    folder = _recipe(tmp_path, "per_model:\n  resnet9000: {model: {hidden_size: 64}}\n  savm: {}\n")
    with pytest.raises(ConfigError, match="unknown model 'resnet9000'"):
        with_recipe({"recipe": "r", "model": {"name": "a3c"}}, folder)
    folder = _recipe(tmp_path, "per_model:\n  savm: {model: {hidden_size: 64}}\n")
    with pytest.raises(ConfigError, match="Did you mean savn"):
        with_recipe({"recipe": "r", "model": {"name": "savn"}}, folder)


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("train: [1, 2]\n", "'train': expected a mapping, got a list"),
        ("per_model: [a3c]\n", "'per_model': expected a mapping, got a list"),
        ("per_model:\n  a3c: [1]\n", "config key 'per_model.a3c': expected a mapping, got a list"),
    ],
)
def test_recipe_sections_of_the_wrong_shape_are_refused_naming_the_key(tmp_path, text, key):
    folder = _recipe(tmp_path, text)
    with pytest.raises(ConfigError, match=key.replace("[", r"\[")):
        with_recipe({"recipe": "r", "model": {"name": "a3c"}}, folder)


def test_a_training_config_whose_model_is_not_a_mapping_is_refused(tmp_path, capsys):
    (tmp_path / "t.yaml").write_text("model: [a3c]\nepisodes: 4\nrecipe: laptop\n")
    assert cli_main(["train", str(tmp_path / "t.yaml"), "--run-dir", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "config key 'model': expected a mapping, got a list" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_experiment_sections_of_the_wrong_shape_are_refused_naming_the_key(tmp_path):
    path = tmp_path / "table1_smoke.yaml"
    path.write_text("experiment: table1\nbudget: smoke\ntrain: [1, 2]\n")
    with pytest.raises(ConfigError, match="config key 'train': expected a mapping, got a list"):
        read_experiment(path)
    path.write_text("experiment: table1\nper_model: {a3c: [1]}\n")
    with pytest.raises(ConfigError, match=r"config key 'per_model\.a3c': expected a mapping"):
        from mapless.experiments.config import train_config

        train_config(read_experiment(path), "a3c", 1)
    path.write_text("experiment: table1\nablations: [1]\n")
    with pytest.raises(ConfigError, match="config key 'ablations': expected a mapping"):
        read_experiment(path)


def test_an_experiment_extending_itself_through_a_relative_path_is_a_circle(tmp_path):
    folder = tmp_path / "ext"
    folder.mkdir()
    (folder / "c.yaml").write_text("extends: ../ext/c.yaml\nexperiment: table1\n")
    with pytest.raises(ConfigError, match="cannot extend in a circle"):
        read_experiment(folder / "c.yaml")
    # A longer circle through another spelling of the same folder.
    (folder / "a.yaml").write_text("extends: ./b.yaml\n")
    (folder / "b.yaml").write_text("extends: ../ext/./a.yaml\n")
    with pytest.raises(ConfigError, match="cannot extend in a circle"):
        read_experiment(folder / "a.yaml")
    # A chain that ends is read.
    (folder / "d.yaml").write_text("extends: ../ext/e.yaml\nseeds: 2\n")
    (folder / "e.yaml").write_text("experiment: table1\nseeds: 3\n")
    config = read_experiment(folder / "d.yaml")
    assert (config.experiment, config.seeds) == ("table1", 2)


def _fake_commands(folder: Path, sinfo_status: int) -> None:
    folder.mkdir(exist_ok=True)
    for name in ("sbatch", "srun", "sinfo"):
        script = folder / name
        code = sinfo_status if name == "sinfo" else 0
        script.write_text(
            f"#!/bin/sh\necho 'slurm_load_partitions: Unable to contact slurm controller' >&2\nexit {code}\n"
        )
        script.chmod(script.stat().st_mode | stat.S_IXUSR)


def test_the_slurm_launcher_without_slurm_is_refused_before_any_run(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert "srun" in slurm_problem() and "not there" in slurm_problem()
    with pytest.raises(MaplessError, match="needs Slurm's sbatch, srun, sinfo on PATH"):
        SlurmLauncher()
    assert SlurmLauncher(cluster="local").cluster == "local"  # the tests' executor needs no Slurm
    # Commands present, scheduler unreachable.
    _fake_commands(tmp_path / "bin", sinfo_status=1)
    monkeypatch.setenv("PATH", str(tmp_path / "bin") + os.pathsep + os.defpath)
    with pytest.raises(MaplessError, match=r"scheduler does not answer \(sinfo: slurm_load_partitions"):
        SlurmLauncher()
    _fake_commands(tmp_path / "bin", sinfo_status=0)
    assert slurm_problem() is None


def test_reproduce_with_the_slurm_launcher_and_no_slurm_exits_2_having_written_nothing(
    tmp_path, monkeypatch, capsys
):
    pytest.importorskip("submitit")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.chdir(tmp_path)
    code = cli_main(
        ["reproduce", "table1", "--budget", "smoke", "--set", "models=[a3c,mlp]", "--launcher", "slurm"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "srun" in err and "Traceback" not in err and "Could not detect" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_published_episode_whose_type_contradicts_its_ids_is_reported_not_exact():
    scene = load_scene("FloorPlan1")
    machine = next(o.id for o in scene.objects if o.type == "CoffeeMachine")
    x, z = (float(v) for v in scene.reachable[0])
    start = (x, z, 0, 0)
    agreeing = RawEpisode(0, "FloorPlan1", "CoffeeMachine", (machine,), start)
    contradicting = RawEpisode(1, "FloorPlan1", "Mug", (machine,), start)
    report = map_episodes([agreeing, contradicting])
    assert report.mapped == 2 and report.exact_episodes == 1
    assert report.contradictions == [(1, f"goal_object_type 'Mug', target ids ['{machine}']")]
    assert [e.target for e in report.episodes] == ["CoffeeMachine", "CoffeeMachine"]  # the ids decide
    assert "type contradicts ids: 1 episode(s)" in report.summary() and "#1: goal_object_type 'Mug'" in (
        report.summary()
    )


def test_the_gym_env_refuses_an_empty_episode_list_at_construction():
    with pytest.raises(MaplessError, match="empty list of episodes"):
        gym.make(mapless.ENV_ID, library=None, episodes=[])
    with pytest.raises(MaplessError, match="empty list of episodes"):
        NavEnv(None, [])
