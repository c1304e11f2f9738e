"""Experiment configurations: the shipped ``<experiment>_<budget>.yaml`` read over
``budgets/<budget>.yaml`` (package data, :mod:`mapless.configs`) -> :class:`ExperimentConfig`, and
the :class:`~mapless.train.config.TrainConfig` of each of an experiment's runs.

A budget file holds what every experiment of that budget shares (training and evaluation
settings, seeds, runs folder, Table 1's model lineup); an experiment file names its budget and holds
only what differs from it, and an experiment that differs in nothing has no file: it is the budget
as it is (``table1_small``). Each layer (budget, experiment file, ``--set``; a file's ``extends:``
first) is read over the one below key by key, nested mappings included (:func:`mapless.config.merge_mappings`,
the one rule); a run's training config is then the recipe the ``train`` block names, ``train`` and
the model's ``per_model`` entry (docs/guide/configuration.md)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from mapless.config import (
    ConfigError,
    Layer,
    apply_overrides,
    from_dict,
    merge_layers,
    read_extending,
    section,
)
from mapless.configs import config_label, configs_dir
from mapless.episodes.protocols import get_protocol
from mapless.errors import MaplessError, UnknownNameError
from mapless.scenes.catalogue import ROOM_TYPES

EXPERIMENTS = ("table1", "table2", "table3", "figure3", "figures45", "layout_shift", "ablation")
BUDGETS = ("smoke", "small", "medium", "long", "full")
ROOM_ABBREV = {"kitchen": "K", "living_room": "L", "bedroom": "Be", "bathroom": "Ba"}


@dataclass(frozen=True)
class ExperimentEval:
    """How runs are evaluated.

    protocol: ``standard`` (select on val, report on test), ``paper`` (select and report on x21-x30)
        or ``reference`` (success within 1.5 m, select on odd x21-x29, report on even x22-x30; its
        runs train under the 1.5 m rule too); mapless.episodes.protocols. Every protocol reads the
        sets of the runs' training target set (``train.env.target_set``, by default the protocol's:
        ``hoz22`` under ``reference``, whose sets are the published HOZ episodes; ``mjolnir22``,
        the paper's targets, whose sets are sampled here, under the others).
    per_room: the first N episodes per room type of the fixed sets (250 = all of the sampled ones;
        of the published HOZ sets of ``hoz22``, up to 1,000 per room type, the first 250 as HOZ
        evaluates).
    select_per_room: the first N per room type of the selection set (None: ``per_room``); selection
        may read a subset while the report reads every episode. The ``paper`` protocol, which selects
        and reports on the same episodes, reads ``per_room`` for both.
    select: evaluate every checkpoint and select (False: the final model only).
    select_file / report_file: episode files replacing the built-in val / test sets (tests), or the
        names of shipped sets; their targets must be the training target set's (refused otherwise).
    shift_layouts: the layout-shift experiment's arrangements of the report split (SOURCE:PER_SCENE,
        mapless.episodes.evalsets; ``gen:3``: three generated arrangements per test floor plan).
    shift_file: an episode file replacing that set, e.g. one made on one's own arrangement files
        with ``mapless episodes make --splits test --layouts FILE:N``.
    within_minutes: Table 1 also chooses each trained run among its snapshots of the first N
        minutes of training, one table per N (the long budget: how the ranking moves with training).
    """

    protocol: Literal["standard", "paper", "reference"] = "standard"
    per_room: int = 250
    select_per_room: int | None = None
    rooms: tuple[str, ...] = ROOM_TYPES
    select: bool = True
    select_file: str | None = None
    report_file: str | None = None
    shift_layouts: str = "gen:3"
    shift_file: str | None = None
    batch_size: int = 32
    workers: int = 2
    seed: int = 0
    greedy: bool = False
    within_minutes: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if any(not isinstance(m, (int, float)) or m <= 0 for m in self.within_minutes):
            raise ConfigError(
                f"config key 'eval.within_minutes': minutes must be > 0, got {list(self.within_minutes)}"
            )
        for key in ("per_room", "batch_size", "workers", "select_per_room"):
            value = getattr(self, key)
            if key == "select_per_room" and value is None:
                continue
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"config key 'eval.{key}': must be an integer >= 1, got {value!r}")
        if self.seed < 0:
            raise ConfigError(
                f"config key 'eval.seed': must be >= 0 (numpy seeds are non-negative), got {self.seed}"
            )
        from mapless.episodes.evalsets import parse_layouts

        try:
            parse_layouts(self.shift_layouts)
        except MaplessError as error:
            raise ConfigError(f"config key 'eval.shift_layouts': {error}") from None


@dataclass(frozen=True)
class AblationRow:
    """One row of the ablation experiment: the focus model changed one way.

    what: the row's one-line description (its label in the report).
    train: TrainConfig overrides of the row's runs (nested mapping, merged over the focus model's
        training config); empty: the focus model's own runs, evaluated differently.
    test_time_adaptation: False evaluates the row's chosen snapshot without test-time adaptation.
    seeds: the row's training seeds (None: the experiment's).
    """

    what: str
    train: dict = field(default_factory=dict)
    test_time_adaptation: bool = True
    seeds: int | None = None

    def __post_init__(self) -> None:
        if not self.train and self.test_time_adaptation:
            raise ConfigError(
                f"ablation row {self.what!r} changes nothing (no train overrides, adaptation on)"
            )
        if self.seeds is not None and self.seeds < 1:
            raise ConfigError(f"ablation row {self.what!r}: seeds must be >= 1, got {self.seeds}")


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment at one budget.

    models: the compared models (Table 1/2, figures); Table 3 always ablates ``focus``.
    seeds: training seeds per run (mean ± std over them).
    model_seeds: seeds of the named models instead of ``seeds`` (Table 1 at the hour: three for a3c
        and cvmeta, two for the rest); an entry of a model outside ``models`` trains nothing.
    train: TrainConfig fields shared by every run (nested mapping, validated by TrainConfig).
    per_model: TrainConfig overrides per model name (e.g. a smaller batch for the meta models).
    rooms: room types of Table 2 (training rooms) and Table 3 (ablated rooms).
    focus: the paper's model (cvmeta), for Table 3 and the showcase figures.
    runs_dir: where training runs go (shared between experiments).
    single_room_scenes: Table 2's training scenes per room type (default ``train:<room>``, the 20
        training floor plans of the room).
    variant_layouts: the layout-shift experiment's second row: ``train.env.layouts`` of the runs
        trained on scene variants (mapless.train.config.LayoutsConfig).
    ablations: the ablation experiment's rows, ``{name: AblationRow fields}``, each the focus model
        changed one way and compared with the focus model's own runs.
    ablation_rows: the rows to run (names of ``ablations``; empty: all), e.g. one lane of two.
    """

    experiment: str = "table1"
    budget: str = "smoke"
    models: tuple[str, ...] = ("random", "a3c", "cvmeta")
    seeds: int = 1
    model_seeds: dict = field(default_factory=dict)
    train: dict = field(default_factory=dict)
    per_model: dict = field(default_factory=dict)
    eval: ExperimentEval = field(default_factory=ExperimentEval)
    rooms: tuple[str, ...] = ROOM_TYPES
    focus: str = "cvmeta"
    runs_dir: str = "runs/experiments"
    gif: bool = True
    single_room_scenes: dict = field(default_factory=dict)
    variant_layouts: dict = field(default_factory=lambda: {"source": "rearrange2023", "fraction": 0.5})
    ablations: dict = field(default_factory=dict)
    ablation_rows: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.experiment not in EXPERIMENTS:
            raise UnknownNameError("experiment", self.experiment, EXPERIMENTS)
        if self.seeds < 1:
            raise ConfigError(f"config key 'seeds': must be >= 1, got {self.seeds}")
        for name, count in self.model_seeds.items():
            # A model left out of the lineup (--set 'models=[...]') keeps its entry, as per_model;
            # a name that is no trained model is a typo.
            if name == "random":
                raise ConfigError("config key 'model_seeds.random': the random agent trains no seeds")
            if not isinstance(count, int) or isinstance(count, bool) or count < 1:
                raise ConfigError(f"config key 'model_seeds.{name}': must be an integer >= 1, got {count!r}")
        if not self.models:  # an experiment of no model trains nothing and reports an empty table
            raise ConfigError("config key 'models': the list is empty; name at least one model")
        from mapless.models import model_class

        for name in (*self.models, self.focus, *self.per_model, *self.model_seeds):
            model_class(name)
        for room in (*self.rooms, *self.eval.rooms):
            if room not in ROOM_TYPES:
                raise UnknownNameError("room type", room, ROOM_TYPES)
        for name in self.ablation_rows:
            if name not in self.ablations:
                raise UnknownNameError("ablation row", name, tuple(self.ablations))
        self.ablation_table()  # each row's fields are checked here

    def seeds_of(self, model: str) -> int:
        """The training seeds of ``model``: its ``model_seeds`` entry, else ``seeds``."""
        return self.model_seeds.get(model, self.seeds)

    def ablation_table(self) -> dict[str, AblationRow]:
        """The ablation rows to run, by name, in the config's order."""
        rows = {}
        for name, fields in self.ablations.items():
            if not isinstance(fields, dict):
                raise ConfigError(f"config key 'ablations.{name}': expected a mapping, got {fields!r}")
            rows[name] = from_dict(AblationRow, fields, prefix=f"ablations.{name}.")
        return {n: r for n, r in rows.items() if not self.ablation_rows or n in self.ablation_rows}


def config_path(experiment: str, budget: str, root: Path | None = None) -> Path:
    """The shipped ``<experiment>_<budget>.yaml`` (or ``root``'s); where there is no such file the
    experiment is the budget as it is (:func:`shipped_experiment`)."""
    return (root or configs_dir()) / f"{experiment}_{budget}.yaml"


def budget_path(budget: str) -> Path:
    """The shipped ``budgets/<budget>.yaml``: what the budget's experiments share."""
    return configs_dir() / "budgets" / f"{budget}.yaml"


def shipped_experiment(experiment: str, budget: str) -> Path | dict:
    """``experiment`` at ``budget`` as shipped: its file, or, where none ships, the budget as it is
    with that experiment (the budget's lineup, runs and settings)."""
    path = config_path(experiment, budget)
    if path.is_file():
        return path
    if experiment not in EXPERIMENTS:
        raise UnknownNameError("experiment", experiment, EXPERIMENTS)
    return {"experiment": experiment, "budget": budget}


def budget_layers(budget: str, directory: Path | None = None) -> list[Layer]:
    """The shipped ``budgets/<budget>.yaml`` (``directory``: the budgets folder, tests) as layers, the
    budgets it ``extends:`` first (``medium`` is ``small`` for longer)."""
    if budget not in BUDGETS:
        raise UnknownNameError("budget", budget, BUDGETS)
    return read_extending((directory or budget_path(budget).parent) / f"{budget}.yaml", config_label)


def read_budget(budget: str, directory: Path | None = None) -> dict:
    """The mapping of a budget, read over the budgets it extends."""
    return merge_layers(budget_layers(budget, directory))[0]


def experiment_layers(source: Path | dict, overrides: list[str] | None = None) -> list[Layer]:
    """The layers of an experiment's configuration, lowest first: the budget it names (with the
    budgets that one extends), the experiment file (with the files it extends; a mapping stands for
    an experiment with no file), then ``--set`` ``overrides``. One naming no budget stands alone."""
    if isinstance(source, Path):
        own = read_extending(source, config_label)
    else:
        own = [(f"the {source.get('budget')} budget as it is (no experiment file)", dict(source))]
    named = merge_layers(own)[0].get("budget")
    below = budget_layers(named) if named is not None else []
    sets = [("--set", apply_overrides({}, overrides))] if overrides else []
    return [*below, *own, *sets]


def read_experiment(source: Path | dict, overrides: list[str] | None = None) -> ExperimentConfig:
    """The experiment file at ``source`` (or a mapping, :func:`shipped_experiment`'s) read over the
    file of the budget it names, then ``overrides``, every layer key by key over the one below
    (:func:`experiment_layers`). The runs' training configs are not checked here
    (:func:`load_experiment` does)."""
    return from_dict(ExperimentConfig, merge_layers(experiment_layers(source, overrides))[0])


def seed_overrides(source: Path | dict, overrides: list[str] | None, seeds: int | None) -> list[str]:
    """``overrides``, then, for ``--seeds N``, ``seeds=N`` and ``model_seeds.M=N`` for every model the
    experiment gives its own count: the command line's seed count is every trained model's."""
    extra = list(overrides or [])
    if seeds is None:
        return extra
    extra.append(f"seeds={seeds}")
    return extra + [f"model_seeds.{m}={seeds}" for m in read_experiment(source, extra).model_seeds]


def load_experiment(
    experiment: str,
    budget: str,
    path: Path | None = None,
    overrides: list[str] | None = None,
    seeds: int | None = None,
) -> ExperimentConfig:
    """The configuration of ``experiment`` at ``budget`` as shipped (or in the file ``path``), with
    every run's training config checked before any work starts: a typo in any model's block fails
    here."""
    if path is not None and not path.is_file():
        raise MaplessError(
            f"no experiment config {path} (experiments: {', '.join(EXPERIMENTS)}; budgets: {', '.join(BUDGETS)})"
        )
    config = read_experiment(path or shipped_experiment(experiment, budget), seed_overrides(
        path or shipped_experiment(experiment, budget), overrides, seeds))  # fmt: skip
    if config.experiment != experiment:
        raise ConfigError(
            f"{path or config_path(experiment, budget)} configures {config.experiment!r}, not {experiment!r}"
        )
    # The per_model blocks of models not compared here too: a misspelt name or key is caught
    # rather than silently ignored.
    for model in sorted({*config.models, config.focus, *config.per_model} - {"random"}):
        train_config(config, model, 1)
        if config.experiment == "layout_shift":
            train_config(config, model, 1, {"env": {"layouts": config.variant_layouts}})
    if config.experiment == "ablation":
        for name, row in config.ablation_table().items():
            try:
                train_config(config, config.focus, 1, row.train)
            except ConfigError as error:
                raise ConfigError(f"ablation row {name!r}: {error}") from None
    return config


#: The layer name of a run's keys taken from the experiment's ``train`` or ``per_model`` block: the
#: source is the experiment layer that set the key there (:func:`mapless.experiments.sources.run_sources`).
FROM_EXPERIMENT = "experiment:"


def run_layers(config: ExperimentConfig, model: str, seed: int, extra: dict | None = None) -> list[Layer]:
    """The layers of one run's training config, lowest first: the recipe the experiment's ``train``
    names (its ``train``, then its ``per_model`` entry for ``model``), the experiment's ``train``,
    its ``per_model[model]``, ``extra`` (a row of the experiment: a room, an ablation), then the
    run's model and seed, with the evaluation protocol's success rule (a run learns the rule it is
    scored by) and its target set where none of those names one (a run learns the classes of the
    episodes it is scored on: the reference protocol's are the published episodes', ``hoz22``)."""
    from mapless.train.recipes import recipe_layers

    own = [
        (f"{FROM_EXPERIMENT}train.", json.loads(json.dumps(config.train))),
        (f"{FROM_EXPERIMENT}per_model.{model}.", section(config.per_model, model, prefix="per_model.")),
        ("the experiment's row", extra or {}),
    ]
    data = merge_layers(own)[0]
    protocol = get_protocol(config.eval.protocol)
    visibility = protocol.visibility_distance
    stated = data.get("env", {}).get("sim", {}).get("visibility_distance", visibility)
    if stated != visibility:
        raise ConfigError(
            f"config key 'train.env.sim.visibility_distance': {stated} contradicts the {config.eval.protocol} "
            f"protocol's success rule ({visibility} m); leave it out, the protocol sets it"
        )
    run = apply_overrides({}, [f"model.name={model}", f"seed={seed}"])
    rule = apply_overrides({}, protocol.train_overrides(data))
    layers = [*own, ("the run (model, seed)", run), (f"eval.protocol {config.eval.protocol}", rule)]
    recipe, layers = recipe_layers(layers)
    return [*recipe, *layers]


def train_config(config: ExperimentConfig, model: str, seed: int, extra: dict | None = None):
    """The TrainConfig of one run, its layers (:func:`run_layers`) read one over the other."""
    from mapless.train.config import train_config_from

    return train_config_from(merge_layers(run_layers(config, model, seed, extra))[0])
