"""The experiments' pipelines: train (or reuse) the runs, evaluate them, write the report."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

from mapless.config import to_dict
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.report import (
    COLUMNS,
    MAIN_COLUMNS,
    ROOM_NAMES,
    details_table,
    difference_record,
    format_difference,
    format_estimate,
    markdown,
    model_record,
    model_table,
    room_table,
    write_json,
)
from mapless.evaluate.stats import seed_estimates
from mapless.experiments.config import ROOM_ABBREV, ExperimentConfig, train_config
from mapless.experiments.evaluator import Evaluator, experiment_scenes
from mapless.experiments.layout_shift import run_layout_shift
from mapless.experiments.runs import RunTally, planned_runs, run_dir_for, train_run
from mapless.files import write_text
from mapless.scenes.catalogue import ROOM_TYPES


def _model_results(config: ExperimentConfig, ev: Evaluator, tally: RunTally, model: str, variant: str = "all",
                   extra: dict | None = None, log: Callable[[str], None] = print) -> tuple[list[list[EpisodeResult]], list[dict]]:  # fmt: skip
    """Per-seed report results of one model (trained per seed, or untrained for ``random``)."""
    per_seed, meta = [], []
    if model == "random":
        results, info = ev.untrained(model)
        return [results], [info]
    for s in range(config.seeds):
        cfg = train_config(config, model, seed=1 + s, extra=extra)
        run_dir = run_dir_for(config, cfg, variant)
        tally.start(model, f"{variant}, seed {1 + s}")
        trained_share = train_run(cfg, run_dir, log)
        results, info = ev.trained(run_dir, cfg)
        tally.finish(trained_share)
        per_seed.append(results)
        meta.append({"run_dir": str(run_dir), **info})
    return per_seed, meta


def _header(config: ExperimentConfig, title: str, ev: Evaluator, command: str) -> list[str]:
    return [
        f"# {title}",
        "",
        f"Budget `{config.budget}`, {config.seeds} training seed(s); {len(ev.report_episodes)} report episodes "
        f"({config.eval.per_room} per room type); protocol: {ev.protocol_label}.",
        f"Command: `{command}`; finished {time.strftime('%Y-%m-%d %H:%M')}.",
        "Cells: mean (± std over seeds) [95 % bootstrap interval over episodes], in %.",
        "",
    ]


def run_table1(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
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
    lines = _header(config, "Table 1: navigation results on unseen scenes", ev, command)
    lines += [model_table(records), "", *_focus_differences(config.focus, records)]
    lines += ["Secondary metrics (mean over seeds):", "", details_table(records), ""]
    for rec in records:
        lines += [f"Per room type, {rec['model']}:", "", room_table(rec), ""]
    return {**_finish(config, ev, out, lines, models=records), "results": results}


def _focus_differences(focus: str, records: list[dict]) -> list[str]:
    """Table 1's comparison of the focus model with each other model, if it has one."""
    key = "focus_minus_model"
    rows = [
        [rec["model"], *(format_difference(c, rec[key][c]) for c in MAIN_COLUMNS)]
        for rec in records
        if key in rec
    ]
    if not rows:
        return []
    header = ["model", *(f"Δ {COLUMNS[c][0]}" for c in MAIN_COLUMNS)]
    return [
        f"{focus} minus each model, in points, with the 95 % interval of the difference over episodes "
        "(paired: the same episodes) and each model's training seeds:",
        "",
        markdown(header, rows),
        "",
    ]


def run_table2(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    """Rows: model x training room type; columns: SR / SPL on each test room type and overall."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    rows, records = [], []
    header = [
        "model",
        "trained on",
        *(f"{ROOM_NAMES[r]} SR / SPL" for r in config.eval.rooms),
        "All SR / SPL",
    ]
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
            records.append(rec)
            cells = []
            for test_room in config.eval.rooms:
                est = rec["rooms"].get(test_room)
                cells.append(_pair(est))
            rows.append([model, f"{ROOM_ABBREV[room]}-single", *cells, _pair(rec["estimates"])])
    lines = _header(
        config, "Table 2: generalisation across room types (train on one, test on all)", ev, command
    )
    lines += [markdown(header, rows), ""]
    return _finish(config, ev, out, lines, runs=records)


def _finish(config: ExperimentConfig, ev: Evaluator, out: Path, lines: list[str], **results) -> dict:
    """Write the experiment's JSON and markdown report; return both."""
    payload = {
        "experiment": config.experiment,
        "config": to_dict(config),
        "protocol": ev.protocol_label,
        **results,
    }
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


def _pair(estimates: dict | None) -> str:
    """``SR [95 % interval] / SPL`` of one cell (the SPL interval is left to the JSON, for width)."""
    if not estimates:
        return "–"
    return f"{format_estimate('success', estimates['success'])} / {format_estimate('spl', estimates['spl'], False)}"


def run_table3(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
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
    header = ["model", *(f"{ROOM_NAMES[r]} SR / SPL" for r in config.eval.rooms), "All SR / SPL"]
    rows = [
        [rec["model"], *(_pair(rec["rooms"].get(r)) for r in config.eval.rooms), _pair(rec["estimates"])]
        for rec in records
    ]
    lines = _header(config, "Table 3: ablation of the hierarchical relationships", ev, command)
    lines += [
        "Each `<Room>_no_relationships` run drops the target->parent edges that only that room type's hierarchy adds to the graph (pairs the VG graph or another room type also links stay) and its parent-object reward.",
        "",
        markdown(header, rows),
        "",
        model_table(records),
        "",
        "Each ablation minus the full model, in points, with the 95 % interval of the difference over "
        "episodes (paired: the same episodes) and both runs' training seeds; the paper's claim is a "
        "drop, largest on the room type whose relationships were removed:",
        "",
        markdown(
            ["model", "Δ SR", "Δ SPL", "Δ SR, its room type", "Δ SPL, its room type"],
            [
                [rec["model"], *_ablation_cells(rec["minus_full"], rec["removed_room"])]
                for rec in records
                if "minus_full" in rec
            ],
        ),
        "",
    ]
    return _finish(config, ev, out, lines, models=records)


def _ablation_cells(minus_full: dict, room: str) -> list[str]:
    return [format_difference(c, minus_full[part][c]) for part in ("all", room) for c in ("success", "spl")]


def run_figure3(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    from mapless.evaluate.figures import exploration_figure

    table = run_table1(dataclasses.replace(config, experiment="table1"), out / "table1", log, command)
    pooled = {m: [r for seed in per_seed for r in seed] for m, per_seed in table["results"].items()}
    curves = exploration_figure(pooled, out / "figure3_exploration.png")
    ratios = {m: seed_estimates(per_seed)["exploration_ratio"] for m, per_seed in table["results"].items()}
    lines = [
        "# Figure 3: ratio of exploration",
        "",
        "Distinct states explored / steps taken, per step index, averaged over the episodes still running.",
        f"Command: `{command}`.",
        "",
        "![ratio of exploration](figure3_exploration.png)",
        "",
        markdown(
            ["model", "final ratio (episode mean)"],
            [[m, format_estimate("exploration_ratio", e)] for m, e in ratios.items()],
        ),
        "",
    ]
    payload = {
        "experiment": config.experiment,
        "curves": curves,
        "final_ratio": {m: e.to_dict() for m, e in ratios.items()},
    }
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


def run_figures45(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    from mapless.evaluate.figures import pick_showcase, trajectory_figure, trajectory_gif
    from mapless.knowledge import parents_of

    table = run_table1(dataclasses.replace(config, experiment="table1"), out / "table1", log, command)
    first_seed = {m: per_seed[0] for m, per_seed in table["results"].items()}
    focus = config.focus if config.focus in first_seed else next(iter(first_seed))
    showcase, failure = pick_showcase(first_seed, focus)
    library = experiment_scenes(config)[0].build()
    lines = ["# Figures 4 and 5: trajectories", "", f"Command: `{command}`.", ""]
    figures = {}
    for name, index, caption in (
        ("figure4_trajectories", showcase, f"{focus} succeeds; the other models on the same episode"),
        ("figure5_failure", failure, f"a failure case of {focus}"),
    ):
        if index is None:
            lines += [f"No episode for {name} ({caption}) in this run.", ""]
            continue
        chosen = {m: next(r for r in res if r.index == index) for m, res in first_seed.items()}
        episode = chosen[focus]
        parents = tuple(parents_of(episode.room_type, episode.target))
        trajectory_figure(chosen, library, out / f"{name}.png", parents=parents)
        figures[name] = {"index": index, "episode_id": episode.episode_id, "scene": episode.scene, "target": episode.target,
                         "parents": list(parents), "outcomes": {m: {"success": r.success, "length": r.length} for m, r in chosen.items()}}  # fmt: skip
        lines += [f"## {name}: {caption}", "", f"{episode.scene}, target {episode.target}, parents {', '.join(parents) or '–'}.", "",
                  f"![{name}]({name}.png)", ""]  # fmt: skip
        if config.gif and name == "figure4_trajectories":
            trajectory_gif(episode, library, out / f"{name}_{focus}.gif", every=1)
            lines += [f"Egocentric views of {focus}: `{name}_{focus}.gif`.", ""]
    payload = {"experiment": config.experiment, "figures": figures}
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


PIPELINES: dict[str, Callable[..., dict]] = {
    "table1": run_table1,
    "table2": run_table2,
    "table3": run_table3,
    "figure3": run_figure3,
    "figures45": run_figures45,
    "layout_shift": run_layout_shift,
}


def _write(out: Path, name: str, payload: dict, lines: list[str]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json(payload, out / f"{name}.json")
    write_text(out / f"{name}.md", "\n".join(lines))


def reproduce(config: ExperimentConfig, reports_dir: Path = Path("reports"), log: Callable[[str], None] = print,
              command: str = "") -> dict:  # fmt: skip
    """Run one experiment end to end; returns the pipeline's payload and markdown. Reports go to
    ``<reports_dir>/<experiment>``, or ``<experiment>-<protocol>`` under a protocol other than the
    standard one, so that a table under two protocols stands side by side."""
    suffix = "" if config.eval.protocol == "standard" else f"-{config.eval.protocol}"
    out = Path(reports_dir) / f"{config.experiment}{suffix}"
    start = time.perf_counter()
    result = PIPELINES[config.experiment](
        config, out, log, command or f"mapless reproduce {config.experiment} --budget {config.budget}"
    )
    log(f"{config.experiment}: done in {time.perf_counter() - start:.0f} s; report in {out}")
    return result
