"""Named training recipes: how each model trains, written once and read by `mapless train` and by
the experiments' budgets alike (no copied config).

A recipe is ``recipes/<name>.yaml`` of the shipped configs (:mod:`mapless.configs`): ``train``
(training-config keys every model gets) and ``per_model`` (keys per model name). A training config
that says ``recipe: NAME`` is read over it: the recipe's ``train``, then its ``per_model`` entry for
the config's model, then the config's own keys, nested mappings key by key (the one merge rule,
:func:`mapless.config.merge_mappings`); the recipe's settings block of the algorithm the config does
not train with (``ppo:`` under ``algo: a3c``) is left out, so ``--set algo=a3c`` over a PPO recipe
trains A3C with the recipe's other keys. What a run then holds is an ordinary training config; the
recipe's name is not kept (its keys are), so a run folder's config says everything it trained with.
"""

from __future__ import annotations

from pathlib import Path

from mapless.config import ConfigError, Layer, apply_overrides, merge_layers, read_mapping, section
from mapless.configs import config_label, configs_dir
from mapless.errors import UnknownNameError
from mapless.models import MODELS, ModelConfig
from mapless.train.config import TrainConfig, train_config_from


def recipes_dir() -> Path:
    """The shipped recipes (package data)."""
    return configs_dir() / "recipes"


def recipe_names(directory: Path | None = None) -> tuple[str, ...]:
    return tuple(sorted(p.stem for p in (directory or recipes_dir()).glob("*.yaml")))


def recipe_layers(layers: list[Layer], directory: Path | None = None) -> tuple[list[Layer], list[Layer]]:
    """The layers of the recipe that ``layers`` (a training config's, lowest first) name with
    ``recipe: NAME`` (none if they name none): its ``train``, then its ``per_model`` entry for the
    config's model, without the settings block of the algorithm the config does not train with;
    and ``layers`` without their ``recipe`` key."""
    data = merge_layers(layers)[0]
    rest = [(label, {k: v for k, v in mapping.items() if k != "recipe"}) for label, mapping in layers]
    name = data.get("recipe")
    if name is None:
        return [], rest
    directory = directory or recipes_dir()
    path = directory / f"{name}.yaml"
    if not path.is_file():
        raise UnknownNameError("recipe", str(name), recipe_names(directory))
    recipe = read_mapping(path)
    unknown = set(recipe) - {"train", "per_model"}
    if unknown:
        raise ConfigError(f"{path}: unknown recipe key {sorted(unknown)[0]!r}; valid: per_model, train")
    per_model = section(recipe, "per_model", str(path))
    for known in per_model:
        if known not in MODELS:  # its settings would apply to no run
            raise ConfigError(f"{path}: per_model: {UnknownNameError('model', known, MODELS)}")
    model = section(data, "model").get("name", ModelConfig.name)
    own = [
        (f"recipe {name}", section(recipe, "train", str(path))),
        (f"recipe {name}, per_model.{model}", section(per_model, model, str(path), "per_model.")),
    ]
    algo = data.get("algo", merge_layers(own)[0].get("algo", TrainConfig.algo))
    unread = {"a3c": "ppo", "ppo": "a3c"}.get(algo)  # an unknown algo is TrainConfig's to refuse
    return [(label, {k: v for k, v in m.items() if k != unread}) for label, m in own], rest


def with_recipe(data: dict, directory: Path | None = None) -> dict:
    """A training-config mapping read over the recipe it names (unchanged if it names none)."""
    recipe, rest = recipe_layers([("config", data)], directory)
    return merge_layers([*recipe, *rest])[0]


def train_file_layers(path: str | Path | None, overrides: list[str] | None = None) -> list[Layer]:
    """The layers of ``mapless train CONFIG --set ...``, lowest first: the recipe the file (or
    ``--set``) names, the file, ``--set``."""
    layers = [(config_label(Path(path)), read_mapping(path))] if path is not None else []
    if overrides:
        layers.append(("--set", apply_overrides({}, overrides)))
    recipe, rest = recipe_layers(layers)
    return [*recipe, *rest]


def load_train_config(path: str | Path | None, overrides: list[str] | None = None) -> TrainConfig:
    """A training config file with ``--set`` overrides, read over its recipe (overrides apply first,
    so ``--set model.name=X`` picks model X's recipe)."""
    return train_config_from(merge_layers(train_file_layers(path, overrides))[0])
