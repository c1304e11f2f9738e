"""The layout-shift experiment: do agents find objects that have moved?

Each model is trained twice, on the default arrangements (the paper's protocol: Table 1's run, reused
when it exists) and on scene variants (``variant_layouts``: a mix of default and other arrangements
of the training floor plans), selected on the val episodes of the default arrangements, and reported
on the test floor plans under their default arrangements and under other ones (``eval.shift_layouts``:
generated arrangements; or ``eval.shift_file``: episodes on one's own arrangement files).

Paired intervals (the same episodes on both sides): each model's variant row minus its default row,
and the focus model minus each other model on both sets, which says whether the focus model's
advantage (cvmeta's hierarchical parent objects) grows or vanishes when objects move.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.report import (
    COLUMNS,
    MAIN_COLUMNS,
    difference_record,
    format_difference,
    markdown,
    model_record,
    model_table,
)
from mapless.experiments.config import ExperimentConfig, train_config
from mapless.experiments.evaluator import Evaluator
from mapless.experiments.runs import RunTally, planned_runs, run_dir_for, train_run

ROWS = ("default", "variants")
SETS = ("default", "shifted")
PerSeed = list[list[EpisodeResult]]


def _row(
    config: ExperimentConfig, ev: Evaluator, tally: RunTally, model: str, row: str, log: Callable[[str], None]
) -> tuple[dict[str, PerSeed], list[dict]]:
    """One model trained one way: per-seed results on the default and the shifted test set."""
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
        out["shifted"].append(ev.on(ev.shift_episodes, model, cfg, chosen))
        tally.finish(trained_share)
        meta.append({"run_dir": str(run_dir), "model_file": chosen, **info})
    return out, meta


def run_layout_shift(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    from mapless.experiments.pipelines import _finish, _header

    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    results: dict[tuple[str, str], dict[str, PerSeed]] = {}
    records = []
    for model in config.models:
        for row in ROWS if model != "random" else ROWS[:1]:
            log(f"{model}, trained on {row} arrangements:")
            per_set, meta = _row(config, ev, tally, model, row, log)
            results[model, row] = per_set
            for name in SETS:
                label = f"{model} | {row} | {name}"
                records.append(
                    model_record(label, per_set[name], {"runs": meta, "trained_on": row, "test_on": name})
                )
    shift = config.eval.shift_file or config.eval.shift_layouts
    lines = _header(config, "Layout shift: the test floor plans under other arrangements", ev, command)
    lines += [
        f"Shifted set: {len(ev.shift_episodes)} episodes on the test floor plans under `{shift}`; "
        f"variant training: `env.layouts` = {config.variant_layouts}.",
        "Rows `model | trained on | tested on`; selection on val under the default arrangements.",
        "",
        model_table(records),
        "",
    ]
    variant_rows = _differences(
        [
            (model, results[model, "default"][name], results[model, "variants"][name], name)
            for model in config.models
            if (model, "variants") in results
            for name in SETS
        ]
    )
    focus_rows = _differences(
        [
            (f"{config.focus} − {m} ({row})", results[m, row][s], results[config.focus, row][s], s)
            for (m, row) in results
            if m != config.focus and (config.focus, row) in results
            for s in SETS
        ]
    )
    lines += [
        "Trained on variants minus trained on default arrangements, in points, paired over the same "
        "episodes (and seeds):",
        "",
        variant_rows["markdown"],
        "",
        f"{config.focus} minus each model, on the default and on the shifted test set (paired): does its "
        "advantage grow or vanish when objects move?",
        "",
        focus_rows["markdown"],
        "",
    ]
    return _finish(
        config,
        ev,
        out,
        lines,
        models=records,
        variants_minus_default=variant_rows["records"],
        focus_minus_model=focus_rows["records"],
    )


def _differences(pairs: list[tuple[str, PerSeed, PerSeed, str]]) -> dict:
    """Markdown and JSON of B minus A for each ``(label, A, B, test set)``."""
    header = ["comparison", "tested on", *(f"Δ {COLUMNS[c][0]}" for c in MAIN_COLUMNS)]
    rows, records = [], []
    for label, a, b, name in pairs:
        diff = difference_record(a, b)
        records.append({"comparison": label, "test_on": name, **diff})
        rows.append([label, name, *(format_difference(c, diff[c]) for c in MAIN_COLUMNS)])
    return {"markdown": markdown(header, rows) if rows else "(none)", "records": records}
