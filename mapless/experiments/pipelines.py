"""The experiments' pipelines: train (or reuse) the runs, evaluate them, and return what they found
as records (records.py); :func:`reproduce` has render.py write the report."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from mapless.evaluate.report import ROOM_NAMES, difference_record, model_record
from mapless.evaluate.stats import seed_estimates
from mapless.experiments.config import ROOM_ABBREV, ExperimentConfig, train_config
from mapless.experiments.evaluator import Evaluator, experiment_scenes
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
from mapless.experiments.runs import RunTally, planned_runs, run_dir_for, train_run
from mapless.scenes.catalogue import ROOM_TYPES


def _model_results(config: ExperimentConfig, ev: Evaluator, tally: RunTally, model: str, variant: str = "all",
                   extra: dict | None = None, log: Callable[[str], None] = print,
                   seeds: int | None = None) -> tuple[PerSeed, list[dict]]:  # fmt: skip
    """Per-seed report results of one model (trained per seed, or untrained for ``random``)."""
    per_seed, meta = [], []
    if model == "random":
        results, info = ev.untrained(model)
        return [results], [info]
    for s in range(seeds or config.seeds):
        cfg = train_config(config, model, seed=1 + s, extra=extra)
        run_dir = run_dir_for(config, cfg, variant)
        tally.start(model, f"{variant}, seed {1 + s}")
        trained_share = train_run(cfg, run_dir, log)
        results, info = ev.trained(run_dir, cfg)
        tally.finish(trained_share)
        per_seed.append(results)
        meta.append({"run_dir": str(run_dir), **info})
    return per_seed, meta


def _setting(config: ExperimentConfig, ev: Evaluator) -> Setting:
    return Setting(config, ev.protocol_label, len(ev.report_episodes))


def table1(config: ExperimentConfig, log: Callable[[str], None]) -> Table1:
    """Every model of the config on the report episodes, and the focus model minus each other."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    records, results = [], {}
    for model in config.models:
        log(f"{model}:")
        per_seed, meta = _model_results(config, ev, tally, model, log=log)
        records.append(model_record(model, per_seed, {"runs": meta, "protocol": config.eval.protocol}))
        results[model] = per_seed
    if config.focus in results:
        for rec in records:
            if rec["model"] != config.focus:
                rec["focus_minus_model"] = difference_record(results[rec["model"]], results[config.focus])
    return Table1(_setting(config, ev), records, results)


def table2(config: ExperimentConfig, log: Callable[[str], None]) -> Table2:
    """One run per model and training room type, each tested on every room type."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    rows = []
    for model in config.models:
        for room in config.rooms:
            log(f"{model}, {ROOM_ABBREV[room]}-single:")
            extra = {"env": {"scenes": config.single_room_scenes.get(room, f"train:{room}")}}
            per_seed, meta = _model_results(
                config, ev, tally, model, f"{ROOM_ABBREV[room]}-single", extra, log
            )
            rec = model_record(
                f"{model} {ROOM_ABBREV[room]}-single",
                per_seed,
                {"runs": meta, "train_room": room},
                keep_episodes=False,
            )
            rows.append(Table2Row(model, room, rec))
    return Table2(_setting(config, ev), rows)


def table3(config: ExperimentConfig, log: Callable[[str], None]) -> Table3:
    """The focus model with every room's relationships, then without those of one room type."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    variants = [("full", None)] + [(room, tuple(r for r in ROOM_TYPES if r != room)) for room in config.rooms]
    records, full = [], None
    for name, rooms in variants:
        label = config.focus if rooms is None else f"{ROOM_NAMES[name].replace(' ', '_')}_no_relationships"
        log(f"{label}:")
        extra = (
            None
            if rooms is None
            else {"model": {"hierarchy_rooms": list(rooms)}, "env": {"parent_reward_rooms": list(rooms)}}
        )
        # The unablated model is Table 1's run (variant "all", same configuration): trained once.
        per_seed, meta = _model_results(
            config, ev, tally, config.focus, "all" if rooms is None else f"no-{name}", extra, log
        )
        rec = model_record(
            label,
            per_seed,
            {"runs": meta, "removed_room": None if rooms is None else name},
            keep_episodes=False,
        )
        if rooms is None:
            full = per_seed
        else:
            rec["minus_full"] = {
                "all": difference_record(full, per_seed),
                name: difference_record(full, per_seed, name),
            }
        records.append(rec)
    return Table3(_setting(config, ev), records)


def ablation(config: ExperimentConfig, log: Callable[[str], None]) -> Ablation:
    """The focus model, then each row of ``config.ablations``: trained with the row's overrides
    (its own runs), or the focus model's chosen snapshots evaluated without test-time adaptation;
    every row minus the focus model, paired over the same episodes and seeds."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    focus = config.focus
    log(f"{focus}:")
    # The unablated model is Table 1's run (variant "all", same configuration): trained once.
    full, full_meta = _model_results(config, ev, tally, focus, log=log)
    records = [model_record(focus, full, {"runs": full_meta, "row": "focus"})]
    for name, row in config.ablation_table().items():
        log(f"{focus}, {name} ({row.what}):")
        if row.train:
            per_seed, meta = _model_results(
                config, ev, tally, focus, f"ablation-{name}", row.train, log, row.seeds
            )
            baseline = full[: len(per_seed)]
        else:
            per_seed, meta, baseline = [], [], full
        if not row.test_time_adaptation:
            runs = meta or full_meta
            per_seed = [_unadapted(config, ev, focus, name, row, run, 1 + s) for s, run in enumerate(runs)]
            meta = [{"run_dir": run["run_dir"], "model_file": ev.chosen_model(Path(run["run_dir"]), run)}
                    for run in runs]  # fmt: skip
        rec = model_record(f"{focus}: {row.what}", per_seed, {"runs": meta, "row": name, "what": row.what})
        # Paired over the focus model's seeds of the same numbers (a one-seed row: the first seed).
        rec["minus_focus"] = difference_record(baseline[: len(per_seed)], per_seed)
        records.append(rec)
    return Ablation(_setting(config, ev), records)


def _unadapted(
    config: ExperimentConfig, ev: Evaluator, focus: str, name: str, row, run: dict, seed: int
) -> list:
    """A run's chosen snapshot on the report episodes, never adapted at test time."""
    cfg = train_config(config, focus, seed=seed, extra=row.train or None)
    chosen = ev.chosen_model(Path(run["run_dir"]), run)
    cache = Path(run["run_dir"]) / "eval" / f"unadapted_{Path(chosen).stem}_{len(ev.report_episodes)}.json"
    return ev.on(ev.report_episodes, focus, cfg, chosen, cache, adapt=False)


def figure3(config: ExperimentConfig, log: Callable[[str], None]) -> Figure3:
    """Table 1's records, and each model's final ratio of exploration."""
    table = table1(config, log)
    ratios = {m: seed_estimates(per_seed)["exploration_ratio"] for m, per_seed in table.results.items()}
    return Figure3(table, ratios)


def figures45(config: ExperimentConfig, log: Callable[[str], None]) -> Figures45:
    """Table 1's records, and the episodes of Figure 4 (the focus model succeeds where most others
    fail) and Figure 5 (a failure of the focus model), each as every model ran it on its first seed."""
    from mapless.evaluate.figures import pick_showcase
    from mapless.knowledge import parents_of

    table = table1(config, log)
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
SHIFT_ROWS = ("default", "variants")
SHIFT_SETS = ("default", "shifted")


def _shift_row(config: ExperimentConfig, ev: Evaluator, tally: RunTally, model: str, row: str,
               log: Callable[[str], None]) -> tuple[dict[str, PerSeed], list[dict]]:  # fmt: skip
    """One model trained one way (``row``): per-seed results on the default and the shifted test set."""
    if model == "random":
        results, info = ev.untrained(model)
        return {"default": [results], "shifted": [ev.on(ev.shift_episodes, model)]}, [info]
    extra = None if row == "default" else {"env": {"layouts": config.variant_layouts}}
    out: dict[str, PerSeed] = {"default": [], "shifted": []}
    meta = []
    for s in range(config.seeds):
        cfg = train_config(config, model, seed=1 + s, extra=extra)
        # The default row's runs are Table 1's ("all"), so that a finished Table 1 is reused.
        run_dir = run_dir_for(config, cfg, "all" if row == "default" else "layouts")
        tally.start(model, f"{row} arrangements, seed {1 + s}")
        trained_share = train_run(cfg, run_dir, log)
        results, info = ev.trained(run_dir, cfg)
        chosen = ev.chosen_model(run_dir, info)
        out["default"].append(results)
        cache = run_dir / "eval" / f"shifted_{Path(chosen).stem}.json"
        out["shifted"].append(ev.on(ev.shift_episodes, model, cfg, chosen, cache))
        tally.finish(trained_share)
        meta.append({"run_dir": str(run_dir), "model_file": chosen, **info})
    return out, meta


def layout_shift(config: ExperimentConfig, log: Callable[[str], None]) -> LayoutShift:
    """Do agents find objects that have moved? Each model trained on the default arrangements (the
    paper's protocol: Table 1's run, reused when it exists) and on scene variants (``variant_layouts``),
    selected on the val episodes of the default arrangements, reported on the test floor plans under
    their default arrangements and under other ones (``eval.shift_layouts``, or ``eval.shift_file``).
    Paired intervals: each model's variants row minus its default row, and the focus model minus each
    other model on both sets (does the focus model's advantage grow or vanish when objects move?)."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    results: dict[tuple[str, str], dict[str, PerSeed]] = {}
    records = []
    for model in config.models:
        for row in SHIFT_ROWS if model != "random" else SHIFT_ROWS[:1]:
            log(f"{model}, trained on {row} arrangements:")
            per_set, meta = _shift_row(config, ev, tally, model, row, log)
            results[model, row] = per_set
            for name in SHIFT_SETS:
                label = f"{model} | {row} | {name}"
                records.append(
                    model_record(label, per_set[name], {"runs": meta, "trained_on": row, "test_on": name})
                )
    variants = [
        _comparison(model, results[model, "default"][name], results[model, "variants"][name], name)
        for model in config.models
        if (model, "variants") in results
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


PIPELINES: dict[str, Callable[[ExperimentConfig, Callable[[str], None]], object]] = {
    "table1": table1,
    "table2": table2,
    "table3": table3,
    "figure3": figure3,
    "figures45": figures45,
    "layout_shift": layout_shift,
    "ablation": ablation,
}


def reproduce(config: ExperimentConfig, reports_dir: Path = Path("reports"), log: Callable[[str], None] = print,
              command: str = "") -> dict:  # fmt: skip
    """Run one experiment end to end; returns its report's payload and markdown. Reports go to
    ``<reports_dir>/<experiment>``, or ``<experiment>-<protocol>`` under a protocol other than the
    standard one, so that a table under two protocols stands side by side."""
    suffix = "" if config.eval.protocol == "standard" else f"-{config.eval.protocol}"
    out = Path(reports_dir) / f"{config.experiment}{suffix}"
    start = time.perf_counter()
    record = PIPELINES[config.experiment](config, log)
    command = command or f"mapless reproduce {config.experiment} --budget {config.budget}"
    result = write_report(config.experiment, record, out, command)
    log(f"{config.experiment}: done in {time.perf_counter() - start:.0f} s; report in {out}")
    return result
