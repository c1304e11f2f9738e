"""The shipped configurations are package data (mapless/configs), found wherever mapless is installed,
and `mapless train CONFIG` tells a path from a shipped config's name by one rule."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapless.cli import main
from mapless.configs import configs_dir, train_config_file, train_config_names
from mapless.errors import UnknownNameError


def test_the_configs_live_inside_the_package() -> None:
    import mapless

    assert configs_dir().parent == Path(mapless.__file__).parent
    assert (configs_dir() / "budgets" / "smoke.yaml").is_file()
    assert (configs_dir() / "recipes" / "laptop.yaml").is_file()
    assert {"train_ppo", "train_smoke", "train_cvmeta"} <= set(train_config_names())


def test_a_name_is_a_shipped_config_and_a_slash_or_yaml_suffix_makes_a_path() -> None:
    assert train_config_file("train_ppo") == configs_dir() / "train_ppo.yaml"
    # The same words as a path: read from the current folder, never swapped for the shipped file.
    assert train_config_file("train_ppo.yaml") == Path("train_ppo.yaml")
    assert train_config_file("./train_ppo") == Path("train_ppo")
    assert train_config_file("configs/mine.yml") == Path("configs/mine.yml")
    with pytest.raises(UnknownNameError, match=r"'train_pp'.*Did you mean train_ppo"):
        train_config_file("train_pp")


def test_mapless_train_reads_a_shipped_config_by_name(tmp_path: Path, capsys) -> None:
    runs = tmp_path / "runs"
    # The shipped train_smoke read by name (seed -1 stops it before any training).
    assert main(["train", "train_smoke", "--set", "seed=-1", "--runs-root", str(runs)]) == 2
    assert "config key 'seed': must be >= 0" in capsys.readouterr().err and not runs.exists()
    assert main(["train", "no_such_config", "--runs-root", str(runs)]) == 2
    err = capsys.readouterr().err
    assert "unknown shipped training config 'no_such_config'" in err and "train_smoke" in err
    assert main(["train", str(tmp_path / "missing.yaml"), "--runs-root", str(runs)]) == 2
    assert "missing.yaml" in capsys.readouterr().err
