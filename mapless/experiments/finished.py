"""``mapless reproduce --no-train``: an experiment reported from the runs it finds finished, never
training one. A model whose first seeds are finished is reported on those seeds; the rows with no
finished seed are left out of the report, and each run that would have been trained is named."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

from mapless.errors import MaplessError
from mapless.experiments.config import ExperimentConfig
from mapless.experiments.launch import PlannedRun


def finished_only(config: ExperimentConfig, log: Callable[[str], None] = print) -> ExperimentConfig:
    """``config`` without the models (Table 3: rooms; the ablation: rows) whose runs are not all
    finished; the focus model of Table 3 and the ablation, with which every row is compared, must be."""
    from mapless.experiments.pipelines import ROWS

    rows = ROWS[config.experiment](config)
    unfinished = {key: [r for r in row.runs(config) if not r.finished] for key, row in rows.items()}
    unfinished = {key: runs for key, runs in unfinished.items() if runs}
    if not unfinished:
        return config
    for runs in unfinished.values():
        for run in runs:
            log(f"not trained (--no-train): {run.label} would go to {run.run_dir}")
    if config.experiment in ("table3", "ablation"):
        if None in unfinished:
            raise MaplessError(
                f"--no-train: the runs of {config.focus}, with which every row is compared, are not all "
                "finished; nothing to report"
            )
        if config.experiment == "table3":
            return dataclasses.replace(config, rooms=tuple(r for r in config.rooms if r not in unfinished))
        kept = tuple(name for name in config.ablation_table() if name not in unfinished)
        if not kept:  # an empty list would mean every row
            raise MaplessError("--no-train: no ablation row has its runs finished; nothing to report")
        return dataclasses.replace(config, ablation_rows=kept)
    finished_seeds = _finished_seeds(config, rows)
    dropped = {m for m, count in finished_seeds.items() if count == 0}
    models = tuple(m for m in config.models if m not in dropped)
    if all(m == "random" for m in models):
        raise MaplessError("--no-train: no trained model has its runs finished; nothing to report")
    fewer = {m: n for m, n in finished_seeds.items() if m in models and n < config.seeds_of(m)}
    partly = ", ".join(f"{m} on {n} of {config.seeds_of(m)} seeds" for m, n in fewer.items())
    log(
        f"--no-train: reporting {', '.join(models)}"
        + (f" ({partly})" if partly else "")
        + (f" (left out: {', '.join(sorted(dropped))})" if dropped else "")
    )
    return dataclasses.replace(config, models=models, model_seeds={**config.model_seeds, **fewer})


def _finished_seeds(config: ExperimentConfig, rows: dict) -> dict[str, int]:
    """For each trained model, how many of its first seeds are finished in every row it has (seed 3
    finished without seed 2 counts 1: a report's seeds are always 1..N)."""
    counts: dict[str, int] = {}
    for key, row in rows.items():
        runs = row.runs(config)
        if not runs:  # random trains nothing
            continue
        model = key[0] if isinstance(key, tuple) else key
        prefix = next((i for i, run in enumerate(runs) if not run.finished), len(runs))
        counts[model] = min(counts.get(model, prefix), prefix)
    return counts


class NoTraining:
    """A launcher that trains nothing: every run must be finished already (:func:`finished_only`)."""

    def train(self, runs: Sequence[PlannedRun], log: Callable[[str], None]) -> bool:
        todo = [run for run in runs if not run.finished]
        if todo:
            raise MaplessError(f"--no-train: {todo[0].label} is not finished ({todo[0].run_dir})")
        for run in runs:
            log(f"  reusing finished run {run.run_dir}")
        return True
