"""Named training recipes (mapless/configs/recipes/): `mapless train` and the budgets read the same
per-model settings, in a fixed order of precedence, and bad recipes are clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapless.config import ConfigError, to_dict
from mapless.configs import configs_dir
from mapless.experiments import load_experiment, train_config
from mapless.train.recipes import load_train_config, recipe_names, with_recipe

ROOT = Path(__file__).resolve().parent.parent
RUN_LENGTH = (
    "frames",
    "max_seconds",
    "checkpoint_every",
    "log_every",
    "progress",
    "threads",
    "seed",
    "episodes",
)


@pytest.mark.parametrize("model", ["cvmeta", "a3c", "mjolnir_o", "mlp"])
def test_the_one_run_recipe_trains_a_model_as_the_small_budget_does(model: str) -> None:
    """`mapless train train_ppo --set model.name=X` and the small budget's run of X
    differ only in how long they train and where the run goes."""
    one_run = load_train_config(configs_dir() / "train_ppo.yaml", [f"model.name={model}"])
    budget = train_config(load_experiment("table1", "small"), model, seed=1)
    one_run_dict, budget_dict = to_dict(one_run), to_dict(budget)
    for key in RUN_LENGTH:
        del one_run_dict[key], budget_dict[key]
    assert one_run_dict == budget_dict
    assert one_run.max_seconds == budget.max_seconds == 900


def test_a_config_reads_over_its_recipe_and_overrides_over_the_config(tmp_path: Path) -> None:
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    (recipes / "mine.yaml").write_text(
        "train: {algo: ppo, ppo: {lr: 0.001, epochs: 2}}\n"
        "per_model: {cvmeta: {ppo: {epochs: 3}, model: {gcn_hidden: 32}}}\n"
    )
    data = {"recipe": "mine", "model": {"name": "cvmeta", "gcn_hidden": 16}, "ppo": {"clip": 0.1}}
    merged = with_recipe(data, recipes)
    assert merged == {
        "algo": "ppo",
        "ppo": {"lr": 0.001, "epochs": 3, "clip": 0.1},  # recipe < its per_model entry < the config
        "model": {"name": "cvmeta", "gcn_hidden": 16},
    }
    assert "recipe" in data  # the input is not modified
    other = with_recipe({"recipe": "mine", "model": {"name": "a3c"}}, recipes)
    assert other["ppo"] == {"lr": 0.001, "epochs": 2}
    assert with_recipe({"model": {"name": "a3c"}}, recipes) == {"model": {"name": "a3c"}}


def test_bad_recipes_are_clear_errors(tmp_path: Path) -> None:
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    (recipes / "typo.yaml").write_text("trian: {algo: ppo}\n")
    with pytest.raises(ConfigError, match="unknown recipe key 'trian'"):
        with_recipe({"recipe": "typo"}, recipes)
    with pytest.raises(KeyError, match="typo"):  # the valid names are listed
        with_recipe({"recipe": "missing"}, recipes)
    assert "laptop" in recipe_names()
