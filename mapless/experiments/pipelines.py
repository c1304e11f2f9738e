"""The experiments' pipelines. Each experiment's rows (a model trained one way: a line of its
report) name its runs; :func:`reproduce` has a launcher (launch.py) train them all (or reuse them),
then the pipeline evaluates them in its rows' order and returns what it found as records
(records.py), which render.py writes as the report."""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapless.checkpoint import training_log
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import episodes_digest
from mapless.evaluate.metrics import compared_metrics, same_actions
from mapless.evaluate.report import ROOM_NAMES, difference_record, model_record
from mapless.evaluate.selection import cache_file
from mapless.evaluate.stats import seed_estimates
from mapless.experiments.config import ROOM_ABBREV, ExperimentConfig, train_config
from mapless.experiments.evaluator import EvaluateInLane, Evaluator, experiment_scenes
from mapless.experiments.launch import Launcher, LocalLauncher, PlannedRun, distinct
from mapless.experiments.records import (
    Ablation,
    Figure3,
    Figures45,
    LayoutShift,
    PerSeed,
    Setting,
    Table1,
    Table2,
    Table2Row,
    Table3,
    TrajectoryFigure,
)
from mapless.experiments.render import write_report
from mapless.files import unwritable
from mapless.models import MODELS
from mapless.models.settings import reads
from mapless.scenes.catalogue import ROOM_TYPES


@dataclass(frozen=True)
class Row:
    """A model trained one way (``variant``: the folder name of the ``extra`` training overrides):
    a line of a report, with one run per seed (``seeds``; None: the experiment's), none for random."""

    model: str
    variant: str = "all"
    extra: dict | None = None
    seeds: int | None = None

    def runs(self, config: ExperimentConfig) -> list[PlannedRun]:
        if self.model == "random":
            return []
        return [
            PlannedRun.of(config, self.model, self.variant, 1 + s, self.extra)
            for s in range(self.seeds or config.seeds_of(self.model))
        ]


def _model_results(
    config: ExperimentConfig, ev: Evaluator, row: Row, within_minutes: float | None = None
) -> tuple[PerSeed, list[dict]]:
    """Per-seed report results of one row (its trained runs, each chosen among its snapshots of
    the first ``within_minutes`` of training if given, or ``random`` untrained)."""
    if row.model == "random":
        results, info = ev.untrained(row.model)
        return [results], [info]
    per_seed, meta = [], []
    for run in row.runs(config):
        results, info = ev.trained(run.run_dir, run.config, within_minutes)
        per_seed.append(results)
        meta.append({"run_dir": str(run.run_dir), **info})
        if within_minutes is None:
            meta[-1]["training"] = training_curve(run.run_dir)
    return per_seed, meta


#: The training log's scalars a report draws (mapless.train.monitor): the share of training episodes
#: ended by a successful Done, and the policy's mean entropy per step.
TRAINING_CURVE = {"success": "charts/success", "entropy": "losses/entropy"}


#: PPO's statistics of its updates (mapless.train.ppo), logged by the runs PPO trains: how far an
#: update moved the policy from the one that acted (the approximate KL), the share of probability
#: ratios clipped, and the share of the returns' variance the critic explains.
UPDATE_STATS = {
    "approx_kl": "ppo/approx_kl",
    "clip_fraction": "ppo/clip_fraction",
    "explained_variance": "ppo/explained_variance",
}


def training_curve(run_dir: Path) -> dict:
    """A run's :data:`TRAINING_CURVE` at every record of its training log, with its frames and
    training minutes, as a report keeps it (rounded: it is drawn, not computed on); and, where PPO
    trained it, ``updates``: the mean of each of :data:`UPDATE_STATS` over its records."""
    log = training_log(run_dir, tuple(TRAINING_CURVE.values()))
    curve: dict = {
        "frames": log["frames"],
        "minutes": [round(s / 60, 3) for s in log["seconds"]],
        **{name: [round(v, 4) for v in log[key]] for name, key in TRAINING_CURVE.items()},
    }
    updates = training_log(run_dir, tuple(UPDATE_STATS.values()))
    if updates["frames"]:
        curve["updates"] = {
            name: round(float(np.mean(updates[key])), 5) for name, key in UPDATE_STATS.items()
        }
    return curve


def _setting(config: ExperimentConfig, ev: Evaluator) -> Setting:
    return Setting(config, ev.protocol_label, len(ev.report_episodes))


def table1_rows(config: ExperimentConfig) -> dict[str, Row]:
    """Every model of the config, by name (each with its seeds, :meth:`ExperimentConfig.seeds_of`)."""
    return {model: Row(model) for model in config.models}


def table1(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Table1:
    """Every model of the config on the report episodes, and the focus model minus each other."""
    records, results = [], {}
    for model, row in table1_rows(config).items():
        log(f"{model}:")
        per_seed, meta = _model_results(config, ev, row)
        records.append(model_record(model, per_seed, {"runs": meta, "protocol": config.eval.protocol}))
        results[model] = per_seed
    _focus_minus_each(config.focus, records, results)
    by_minutes = {}
    for minutes in config.eval.within_minutes:
        log(f"chosen within the first {minutes:g} training minutes:")
        capped, capped_results = [], {}
        for model, row in table1_rows(config).items():
            if model == "random":
                continue
            per_seed, meta = _model_results(config, ev, row, minutes)
            meta_record = {"runs": meta, "protocol": config.eval.protocol, "within_minutes": minutes}
            label = f"{model} ≤ {minutes:g} min"
            capped.append(model_record(label, per_seed, meta_record))
            capped_results[label] = per_seed
        _focus_minus_each(f"{config.focus} ≤ {minutes:g} min", capped, capped_results)
        by_minutes[minutes] = capped
    return Table1(_setting(config, ev), records, results, by_minutes)


def _focus_minus_each(focus: str, records: list[dict], results: dict[str, PerSeed]) -> None:
    """Adds ``focus_minus_model`` to every record but the focus model's, if it is among them."""
    if focus in results:
        for rec in records:
            if rec["model"] != focus:
                rec["focus_minus_model"] = difference_record(results[rec["model"]], results[focus])


def table2_rows(config: ExperimentConfig) -> dict[tuple[str, str], Row]:
    """Each model trained on the scenes of one room type, by (model, room type)."""
    return {
        (model, room): Row(
            model,
            f"{ROOM_ABBREV[room]}-single",
            {"env": {"scenes": config.single_room_scenes.get(room, f"train:{room}")}},
        )
        for model in config.models
        for room in config.rooms
    }


def table2(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Table2:
    """One run per model and training room type, each tested on every room type."""
    rows = []
    for (model, room), row in table2_rows(config).items():
        log(f"{model}, {ROOM_ABBREV[room]}-single:")
        per_seed, meta = _model_results(config, ev, row)
        rec = model_record(
            f"{model} {ROOM_ABBREV[room]}-single",
            per_seed,
            {"runs": meta, "train_room": room},
            keep_episodes=False,
        )
        rows.append(Table2Row(model, room, rec))
    return Table2(_setting(config, ev), rows)


def table3_rows(config: ExperimentConfig) -> dict[str | None, Row]:
    """The focus model (key None), then without the relationships of one room type (key: the room)."""
    # The unablated model is Table 1's run (variant "all", same configuration): trained once.
    rows: dict[str | None, Row] = {None: Row(config.focus)}
    # The relationships live in the hierarchical graph of a model that has one, and in the parent
    # reward of every model: a model without the graph is not given a graph setting it never reads.
    model = train_config(config, config.focus, 1).model
    in_graph = reads(MODELS[model.name], model, "hierarchy_rooms")
    for room in config.rooms:
        kept = [r for r in ROOM_TYPES if r != room]
        extra = {"env": {"reward": {"parent_reward_rooms": kept}}}
        if in_graph:
            extra["model"] = {"hierarchy_rooms": kept}
        rows[room] = Row(config.focus, f"no-{room}", extra)
    return rows


def table3(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Table3:
    """The focus model with every room's relationships, then without those of one room type."""
    records, full = [], None
    for name, row in table3_rows(config).items():
        label = config.focus if name is None else f"{ROOM_NAMES[name].replace(' ', '_')}_no_relationships"
        log(f"{label}:")
        per_seed, meta = _model_results(config, ev, row)
        rec = model_record(label, per_seed, {"runs": meta, "removed_room": name}, keep_episodes=False)
        if name is None:
            full = per_seed
        else:
            rec["minus_full"] = {
                "all": difference_record(full, per_seed),
                name: difference_record(full, per_seed, name),
            }
        records.append(rec)
    return Table3(_setting(config, ev), records)


def ablation_rows(config: ExperimentConfig) -> dict[str | None, Row]:
    """The focus model (key None), then each ablation row that trains runs of its own, by name."""
    # The unablated model is Table 1's run (variant "all", same configuration): trained once.
    rows: dict[str | None, Row] = {None: Row(config.focus)}
    for name, row in config.ablation_table().items():
        if row.train:
            rows[name] = Row(config.focus, f"ablation-{name}", row.train, row.seeds)
    return rows


def ablation(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Ablation:
    """The focus model, then each row of ``config.ablations``: trained with the row's overrides
    (its own runs), or the focus model's chosen snapshots evaluated without test-time adaptation;
    every row minus the focus model, paired over the same episodes and seeds."""
    trained = ablation_rows(config)
    focus = config.focus
    log(f"{focus}:")
    full, full_meta = _model_results(config, ev, trained[None])
    records = [model_record(focus, full, {"runs": full_meta, "row": "focus"})]
    for name, row in config.ablation_table().items():
        log(f"{focus}, {name} ({row.what}):")
        if row.train:
            per_seed, meta = _model_results(config, ev, trained[name])
            baseline = full[: len(per_seed)]
        else:
            per_seed, meta, baseline = [], [], full
        if not row.test_time_adaptation:
            runs = meta or full_meta
            per_seed = [_unadapted(config, ev, focus, row, run, 1 + s) for s, run in enumerate(runs)]
            meta = [{"run_dir": run["run_dir"], "model_file": ev.chosen_model(Path(run["run_dir"]), run)}
                    for run in runs]  # fmt: skip
        rec = model_record(f"{focus}: {row.what}", per_seed, {"runs": meta, "row": name, "what": row.what})
        if not row.train:  # the same snapshots and action draws, adapted or not: how much adapting changes
            rec["same_actions"] = [same_actions(a, b) / len(a) for a, b in zip(full, per_seed, strict=True)]
        # Paired over the focus model's seeds of the same numbers (a one-seed row: the first seed),
        # for the metrics the report's difference table shows (false Done too).
        rec["minus_focus"] = difference_record(
            baseline[: len(per_seed)], per_seed, metrics=compared_metrics()
        )
        records.append(rec)
    return Ablation(_setting(config, ev), records)


def _unadapted(config: ExperimentConfig, ev: Evaluator, focus: str, row, run: dict, seed: int) -> list:
    """A run's chosen snapshot on the report episodes, never adapted at test time."""
    cfg = train_config(config, focus, seed=seed, extra=row.train or None)
    chosen = ev.chosen_model(Path(run["run_dir"]), run)
    name = f"unadapted_{Path(chosen).stem}_{len(ev.report_episodes)}"
    cache = cache_file(Path(run["run_dir"]) / "eval", name, episodes_digest(ev.report_episodes))
    return ev.on(ev.report_episodes, focus, cfg, chosen, cache, adapt=False)


def figure3(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Figure3:
    """Table 1's records, and each model's final ratio of exploration."""
    table = table1(config, log, ev)
    ratios = {m: seed_estimates(per_seed)["exploration_ratio"] for m, per_seed in table.results.items()}
    return Figure3(table, ratios)


def figures45(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> Figures45:
    """Table 1's records, and the episodes of Figure 4 (the focus model succeeds where most others
    fail) and Figure 5 (a failure of the focus model), each as every model ran it on its first seed."""
    from mapless.evaluate.figures import pick_showcase
    from mapless.knowledge import parents_of

    table = table1(config, log, ev)
    first_seed = {m: per_seed[0] for m, per_seed in table.results.items()}
    focus = config.focus if config.focus in first_seed else next(iter(first_seed))
    showcase, failure = pick_showcase(first_seed, focus)
    figures = []
    for name, index, caption in (
        ("figure4_trajectories", showcase, f"{focus} succeeds; the other models on the same episode"),
        ("figure5_failure", failure, f"a failure case of {focus}"),
    ):
        if index is None:
            figures.append(TrajectoryFigure(name, caption, None, {}, ()))
            continue
        chosen = {m: next(r for r in res if r.index == index) for m, res in first_seed.items()}
        episode = chosen[focus]
        figures.append(
            TrajectoryFigure(
                name, caption, index, chosen, tuple(parents_of(episode.room_type, episode.target))
            )
        )
    return Figures45(table, focus, figures, experiment_scenes(config)[0])


#: The layout-shift experiment's training rows and test sets.
DEFAULT_ROW, VARIANTS_ROW = SHIFT_ROWS = ("default", "variants")
SHIFT_SETS = ("default", "shifted")


def layout_shift_rows(config: ExperimentConfig) -> dict[tuple[str, str], Row]:
    """Each model trained on the default arrangements and (but random) on scene variants, by
    (model, row of :data:`SHIFT_ROWS`)."""
    rows = {}
    for model in config.models:
        # The default row's runs are Table 1's ("all"), so that a finished Table 1 is reused.
        rows[model, DEFAULT_ROW] = Row(model)
        if model != "random":
            rows[model, VARIANTS_ROW] = Row(model, "layouts", {"env": {"layouts": config.variant_layouts}})
    return rows


def _shift_row(config: ExperimentConfig, ev: Evaluator, row: Row) -> tuple[dict[str, PerSeed], list[dict]]:
    """One model trained one way: per-seed results on the default and the shifted test set."""
    if row.model == "random":
        results, info = ev.untrained(row.model)
        return {"default": [results], "shifted": [ev.on(ev.shift_episodes, row.model)]}, [info]
    out: dict[str, PerSeed] = {"default": [], "shifted": []}
    meta = []
    for run in row.runs(config):
        results, info = ev.trained(run.run_dir, run.config)
        chosen = ev.chosen_model(run.run_dir, info)
        out["default"].append(results)
        name = f"shifted_{Path(chosen).stem}"
        cache = cache_file(run.run_dir / "eval", name, episodes_digest(ev.shift_episodes))
        out["shifted"].append(ev.on(ev.shift_episodes, row.model, run.config, chosen, cache))
        meta.append({"run_dir": str(run.run_dir), "model_file": chosen, **info})
    return out, meta


def layout_shift(config: ExperimentConfig, log: Callable[[str], None], ev: Evaluator) -> LayoutShift:
    """Do agents find objects that have moved? Each model trained on the default arrangements (the
    paper's protocol: Table 1's run, reused when it exists) and on scene variants (``variant_layouts``),
    selected on the val episodes of the default arrangements, reported on the test floor plans under
    their default arrangements and under other ones (``eval.shift_layouts``, or ``eval.shift_file``).
    Paired intervals: each model's variants row minus its default row, and the focus model minus each
    other model on both sets (does the focus model's advantage grow or vanish when objects move?)."""
    results: dict[tuple[str, str], dict[str, PerSeed]] = {}
    records = []
    for (model, trained_on), row in layout_shift_rows(config).items():
        log(f"{model}, trained on {trained_on} arrangements:")
        per_set, meta = _shift_row(config, ev, row)
        results[model, trained_on] = per_set
        for name in SHIFT_SETS:
            label = f"{model} | {trained_on} | {name}"
            meta_set = {"runs": meta, "trained_on": trained_on, "test_on": name}
            records.append(model_record(label, per_set[name], meta_set))
    variants = [
        _comparison(model, results[model, DEFAULT_ROW][name], results[model, VARIANTS_ROW][name], name)
        for model in config.models
        if (model, VARIANTS_ROW) in results
        for name in SHIFT_SETS
    ]
    focus = config.focus
    versus_focus = [
        _comparison(f"{focus} − {m} ({row})", results[m, row][name], results[focus, row][name], name)
        for (m, row) in results
        if m != focus and (focus, row) in results
        for name in SHIFT_SETS
    ]
    return LayoutShift(_setting(config, ev), len(ev.shift_episodes), records, variants, versus_focus)


def _comparison(label: str, a: PerSeed, b: PerSeed, test_on: str) -> dict:
    """B minus A on one test set, paired over the same episodes (and seeds)."""
    return {"comparison": label, "test_on": test_on, **difference_record(a, b)}


#: Each experiment's rows (figures are drawn from Table 1's).
ROWS: dict[str, Callable[[ExperimentConfig], dict]] = {
    "table1": table1_rows,
    "table2": table2_rows,
    "table3": table3_rows,
    "figure3": table1_rows,
    "figures45": table1_rows,
    "layout_shift": layout_shift_rows,
    "ablation": ablation_rows,
}


def experiment_runs(config: ExperimentConfig) -> list[PlannedRun]:
    """Every training run of an experiment, in the order its pipeline evaluates them."""
    return distinct([run for row in ROWS[config.experiment](config).values() for run in row.runs(config)])


def planned_runs(config: ExperimentConfig) -> dict[str, int]:
    """How many training runs an experiment goes through, per model (finished ones are reused, not
    retrained)."""
    return dict(Counter(run.model for run in experiment_runs(config)))


#: Each experiment's pipeline: its records from its trained runs, evaluated by ``ev``.
PIPELINES: dict[str, Callable[[ExperimentConfig, Callable[[str], None], Evaluator], object]] = {
    "table1": table1,
    "table2": table2,
    "table3": table3,
    "figure3": figure3,
    "figures45": figures45,
    "layout_shift": layout_shift,
    "ablation": ablation,
}


def reproduce(config: ExperimentConfig, reports_dir: Path = Path("reports"), log: Callable[[str], None] = print,
              command: str = "", launcher: Launcher | None = None) -> dict | None:  # fmt: skip
    """Run one experiment end to end: ``launcher`` trains its runs (default: side by side on this
    machine's cores, :class:`~mapless.experiments.launch.LocalLauncher`), then they are evaluated
    here in turn. Returns the report's payload and markdown, or None when the runs were left to
    train as jobs not waited for (the same call collects them later). Reports go to
    ``<reports_dir>/<experiment>``, or ``<experiment>-<protocol>`` under a protocol other than the
    standard one, so that a table under two protocols stands side by side."""
    suffix = "" if config.eval.protocol == "standard" else f"-{config.eval.protocol}"
    out = Path(reports_dir) / f"{config.experiment}{suffix}"
    start = time.perf_counter()
    # The report folder and the episode sets are checked before any training: a path that cannot be
    # written or a bad file fails now, not hours on.
    problem = unwritable(out, [f"{config.experiment}.json", f"{config.experiment}.md"])
    if problem is not None:
        raise MaplessError(f"cannot write the report in {out}: {problem} (--reports names another folder)")
    ev = Evaluator(config, log)
    launcher = launcher or LocalLauncher()
    if isinstance(launcher, LocalLauncher) and launcher.evaluate_early is None:
        launcher = dataclasses.replace(launcher, evaluate_early=EvaluateInLane(config))
    if not launcher.train(experiment_runs(config), log):
        return None
    record = PIPELINES[config.experiment](config, log, ev)
    command = command or f"mapless reproduce {config.experiment} --budget {config.budget}"
    result = write_report(config.experiment, record, out, command)
    log(f"{config.experiment}: done in {time.perf_counter() - start:.0f} s; report in {out}")
    return result
