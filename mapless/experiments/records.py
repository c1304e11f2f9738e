"""What each experiment's pipeline finds, as plain records: the pipelines (pipelines.py) produce
them, render.py turns them into the markdown, JSON and figures of ``reports/EXPERIMENT/``.

Model results are :func:`~mapless.evaluate.report.model_record` dicts (estimates over seeds, per
room type, differences), the form the JSON reports keep."""

from __future__ import annotations

from dataclasses import dataclass, field

from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.runner import LibrarySpec
from mapless.evaluate.stats import Estimate
from mapless.experiments.config import ExperimentConfig

#: Per seed, the report episodes' results of one model.
PerSeed = list[list[EpisodeResult]]


@dataclass(frozen=True)
class Setting:
    """What every report states about how its numbers were made."""

    config: ExperimentConfig
    protocol_label: str
    report_episodes: int  # per seed


@dataclass
class Table1:
    """Every model of the config on the report episodes; ``focus_minus_model`` in each other
    model's record when the focus model is among them. ``by_minutes``: the trained models again,
    each run chosen among its snapshots of the first N training minutes (``eval.within_minutes``),
    records labelled ``<model> ≤ <N> min``."""

    setting: Setting
    models: list[dict]
    results: dict[str, PerSeed]  # model -> its episodes, for the figures drawn from Table 1
    by_minutes: dict[float, list[dict]] = field(default_factory=dict)


@dataclass
class Table2Row:
    model: str
    train_room: str
    record: dict  # labelled "<model> <room>-single", with its per-room-type estimates


@dataclass
class Table2:
    """One run per model and training room type, tested on every room type."""

    setting: Setting
    rows: list[Table2Row]


@dataclass
class Table3:
    """The focus model, then without the relationships of one room type at a time (each such
    record with ``removed_room`` and ``minus_full``: its difference from the full model)."""

    setting: Setting
    models: list[dict]


@dataclass
class Ablation:
    """The focus model (its Table 1 runs), then each ablation row: the focus model changed one way,
    each row's record with ``row``, ``what`` and ``minus_focus``, its difference from the focus
    model paired over the same episodes."""

    setting: Setting
    models: list[dict]


@dataclass
class Figure3:
    """Ratio of exploration of Table 1's models."""

    table1: Table1
    final_ratio: dict[str, Estimate]  # model -> the episodes' final exploration ratio


@dataclass
class TrajectoryFigure:
    """One episode of Figure 4 or 5 as every model of Table 1 ran it (first seed), or none found."""

    name: str  # figure4_trajectories or figure5_failure
    caption: str
    index: int | None
    results: dict[str, EpisodeResult]  # model -> its run of the episode
    parents: tuple[str, ...]  # the target's parent objects in its room type


@dataclass
class Figures45:
    """Figure 4 (an episode the focus model succeeds on, where most others fail) and Figure 5 (a
    failure of the focus model), drawn on ``scenes``."""

    table1: Table1
    focus: str
    figures: list[TrajectoryFigure]
    scenes: LibrarySpec


@dataclass
class LayoutShift:
    """Each model trained on the default arrangements and (but ``random``) on scene variants, tested
    on the report episodes (``default``) and on the same split under other arrangements
    (``shifted``): ``models`` are labelled ``model | trained on | tested on``. The differences are
    ``{"comparison", "test_on", **difference_record}`` dicts, paired over the same episodes: each
    model's variants row minus its default row, and the focus model minus each other model."""

    setting: Setting
    shifted_episodes: int  # per seed
    models: list[dict]
    variants_minus_default: list[dict]
    focus_minus_model: list[dict]
