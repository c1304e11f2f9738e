"""``--print-config``: an experiment's resolved configuration and each of its runs' training
configs, every key with the layer it came from (docs/guide/configuration.md)."""

from __future__ import annotations

from pathlib import Path

from mapless.config import format_sources, merge_layers, source_of, to_dict
from mapless.experiments.config import (
    FROM_EXPERIMENT,
    experiment_layers,
    load_experiment,
    run_layers,
    seed_overrides,
    shipped_experiment,
)


def run_sources(run: dict[str, str], experiment: dict[str, str]) -> dict[str, str]:
    """A run's key sources (:func:`~mapless.experiments.config.run_layers`) with the keys taken from
    the experiment's ``train`` and ``per_model`` blocks named by the experiment layer that set them."""
    out = {}
    for path, label in run.items():
        if label.startswith(FROM_EXPERIMENT):
            label = source_of(experiment, label.removeprefix(FROM_EXPERIMENT) + path)
        out[path] = label
    return out


def experiment_text(
    experiment: str,
    budget: str,
    path: Path | None = None,
    overrides: list[str] | None = None,
    seeds: int | None = None,
) -> str:
    """The experiment's keys, then each of its trained rows' training config (seed 1) and run
    folder, each key followed by ``# layer``."""
    from mapless.experiments.pipelines import ROWS

    config = load_experiment(experiment, budget, path, overrides, seeds)  # checks every run
    source = path or shipped_experiment(experiment, budget)
    _, sources = merge_layers(experiment_layers(source, seed_overrides(source, overrides, seeds)))
    shown = {k: v for k, v in to_dict(config).items() if k not in ("train", "per_model")}
    parts = [f"# {experiment} at the {budget} budget", format_sources(shown, sources)]
    seen = set()
    for row in ROWS[config.experiment](config).values():
        if row.model == "random" or (row.model, row.variant) in seen:
            continue
        seen.add((row.model, row.variant))
        _, run = merge_layers(run_layers(config, row.model, 1, row.extra))
        runs = row.runs(config)
        parts.append(f"\n# run {row.model} {row.variant}, seed 1: {runs[0].run_dir if runs else ''}")
        parts.append(format_sources(to_dict(runs[0].config), run_sources(run, sources)))
    return "\n".join(parts)
