"""An experiment's records (records.py) as its report: ``EXPERIMENT.md``, ``EXPERIMENT.json`` and
the figures' PNGs (and GIF) in one folder. Nothing here trains or evaluates."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from mapless.config import to_dict
from mapless.evaluate.metrics import compared_metrics, main_metrics
from mapless.evaluate.published import PAIRS, published_levels
from mapless.evaluate.report import (
    ROOM_NAMES,
    details_table,
    format_difference,
    format_estimate,
    format_value,
    headers,
    markdown,
    model_table,
    room_table,
    write_report_files,
)
from mapless.experiments.config import ROOM_ABBREV
from mapless.experiments.records import (
    Ablation,
    Figure3,
    Figures45,
    LayoutShift,
    Setting,
    Table1,
    Table2,
    Table3,
)
from mapless.provenance import stamp

#: What a renderer returns: the JSON payload and the markdown lines (figures are written on the way).
Rendered = tuple[dict, list[str]]


def write_report(experiment: str, record: object, out: Path, command: str) -> dict:
    """Write ``out/<experiment>.json`` and ``.md`` (and the figures) of one experiment's record;
    returns the payload and the markdown."""
    renderer: Callable[..., Rendered] = RENDERERS[type(record)]
    payload, lines = renderer(experiment, record, out, command)
    payload, text = write_report_files(payload, "\n".join(lines), out / experiment)
    return {"payload": payload, "markdown": text}


def _seed_counts(config) -> str:
    """``2 training seed(s)``, or with the models that train more or fewer: ``… (a3c, cvmeta: 3)``."""
    others = {}
    for model, count in config.model_seeds.items():
        if count != config.seeds and model in config.models:
            others.setdefault(count, []).append(model)
    extra = "; ".join(f"{', '.join(models)}: {count}" for count, models in sorted(others.items()))
    return f"{config.seeds} training seed(s)" + (f" ({extra})" if extra else "")


def _header(setting: Setting, title: str, command: str) -> list[str]:
    config = setting.config
    return [
        f"# {title}",
        "",
        f"Budget `{config.budget}`, {_seed_counts(config)}; {setting.report_episodes} report episodes "
        f"({config.eval.per_room} per room type); protocol: {setting.protocol_label}.",
        stamp(command),
        "Cells: mean (± std over seeds) [95 % bootstrap interval over episodes], in %.",
        "",
    ]


def _payload(experiment: str, setting: Setting, **results) -> dict:
    return {
        "experiment": experiment,
        "config": to_dict(setting.config),
        "protocol": setting.protocol_label,
        **results,
    }


def table1(experiment: str, record: Table1, out: Path, command: str) -> Rendered:
    records = record.models
    lines = _header(record.setting, "Table 1: navigation results on unseen scenes", command)
    lines += [model_table(records), "", *_focus_differences(record.setting.config.focus, records)]
    beside = _beside_published(records) if record.setting.config.eval.protocol == "reference" else []
    lines += _published_table(beside)
    lines += _validation_curves(records, out / f"{experiment}_validation.png")
    lines += training_curves(records, out / f"{experiment}_training.png")
    lines += _by_minutes(record)
    lines += ["Secondary metrics (mean over seeds):", "", details_table(records), ""]
    for rec in records:
        lines += [f"Per room type, {rec['model']}:", "", room_table(rec), ""]
    by_minutes = {f"{m:g}": capped for m, capped in record.by_minutes.items()}
    extra = {"by_minutes": by_minutes} if by_minutes else {}
    if beside:
        extra["published"] = beside
    return _payload(experiment, record.setting, models=records, **extra), lines


def _beside_published(records: list[dict]) -> list[dict]:
    """Each row that has a published level: its seeds' means, the level, and which figures it reaches."""
    levels = published_levels()
    out = []
    for rec in records:
        level = levels.get(rec["model"])
        if level is None:
            continue
        means = {name: rec["estimates"][name]["mean"] for name in main_metrics()}
        out.append(
            {
                "model": rec["model"],
                "seeds": rec["seeds"],
                "means": means,
                "published": dict(level.figures),
                "reached": level.reached(means),
                "source": level.source,
            }
        )
    return out


def _published_table(beside: list[dict]) -> list[str]:
    """The rows beside their published levels (SR / SPL in %, all episodes and L≥5)."""
    if not beside:
        return []
    levels, rows = published_levels(), []
    for row in beside:
        level, means = levels[row["model"]], row["means"]
        measured = {
            k: f"{format_value(a, means[a])} / {format_value(b, means[b])}" for k, (a, b) in PAIRS.items()
        }
        missed = headers([name for name in row["published"] if name not in row["reached"]])
        verdict = "every figure" if not missed else "missed " + ", ".join(missed)
        rows.append(
            [
                row["model"],
                str(row["seeds"]),
                measured["all"],
                level.pair("all"),
                measured["l5"],
                level.pair("l5"),
                verdict,
            ]
        )
    header = ["model", "seeds", "SR / SPL", "published", "L≥5 SR / SPL", "published L≥5", "reached"]
    sources = "; ".join(f"{row['model']}: {row['source']}" for row in beside)
    return [
        "Beside the published levels (the mean over seeds against each published figure, in %; the "
        "references measured theirs on their own episodes under the same 1.5 m rule):",
        "",
        markdown(header, rows),
        "",
        f"Sources: {sources} (mapless/data/published_levels.yaml).",
        "",
    ]


def _by_minutes(record: Table1) -> list[str]:
    """Table 1 again per training-time cap: each run chosen among its snapshots of the first N
    minutes, with when the chosen snapshots were taken."""
    lines = []
    for minutes, capped in record.by_minutes.items():
        lines += [
            f"Chosen among the snapshots of the first {minutes:g} minutes of training (by each run's "
            "log), as if the runs had stopped there:",
            "",
            model_table(capped),
            "",
            *_focus_differences(f"{record.setting.config.focus} ≤ {minutes:g} min", capped),
            "Chosen snapshots (per seed, training minutes / frames): "
            + "; ".join(f"{rec['model']}: {_chosen_snapshots(rec)}" for rec in capped),
            "",
        ]
    return lines


def _chosen_snapshots(rec: dict) -> str:
    cells = []
    for run in rec.get("runs", []):
        selection = run.get("selection")
        if selection is None:
            continue
        chosen = next(c for c in selection["candidates"] if c["path"] == selection["chosen"])
        minutes = "–" if chosen.get("minutes") is None else f"{chosen['minutes']:.0f} min"
        cells.append(f"{minutes} / {chosen.get('frames', -1) / 1e6:.2f}M")
    return ", ".join(cells) or "–"


def _validation_curves(records: list[dict], path: Path) -> list[str]:
    """The figure of every trained model's snapshots on the selection episodes, if they were selected."""
    from mapless.evaluate.figures import validation_figure

    selections = {
        rec["model"]: [run["selection"] for run in rec["runs"] if "selection" in run]
        for rec in records
        if any("selection" in run for run in rec.get("runs", []))
    }
    if not selections or not validation_figure(selections, path):
        return []
    return [
        "How each run learned: success on the selection episodes at every snapshot, against training "
        "frames and minutes (one line per seed; ringed: the snapshot reported above).",
        "",
        f"![validation success per snapshot]({path.name})",
        "",
    ]


def training_curves(records: list[dict], path: Path) -> list[str]:
    """The figure of every trained run's training episodes, and the table that compares the models
    at equal frames: whether one learns less per frame or only sees fewer frames in its minutes."""
    from mapless.evaluate.figures import training_figure

    curves = {
        rec["model"]: [
            run["training"] for run in rec.get("runs", []) if run.get("training", {}).get("frames")
        ]
        for rec in records
    }
    curves = {model: per_seed for model, per_seed in curves.items() if per_seed}
    if not curves or not training_figure(curves, path):
        return []
    fewest = min(curve["frames"][-1] for per_seed in curves.values() for curve in per_seed)
    marks = (fewest / 4, fewest / 2, fewest)

    def over_seeds(per_seed: list[dict], key: str, frames: float | None) -> float:
        return float(np.mean([mean_near(curve, key, frames) for curve in per_seed]))

    rows = [
        [
            model,
            _frames(np.mean([c["frames"][-1] for c in per_seed])),
            *(f"{100 * over_seeds(per_seed, 'success', f):.1f}" for f in (*marks, None)),
            *(f"{over_seeds(per_seed, 'entropy', f):.2f}" for f in (fewest, None)),
        ]
        for model, per_seed in curves.items()
    ]
    header = ["model", "frames trained", *(f"success at {_frames(f)}" for f in marks), "success at its end",
              f"entropy at {_frames(fewest)}", "entropy at its end"]  # fmt: skip
    return [
        "What the training episodes said (the share ended by a successful Done, and the policy's "
        "entropy per step; one line per seed):",
        "",
        f"![training success and entropy]({path.name})",
        "",
        "The same at equal frames (the fewest any run trained, its half and its quarter), and at each "
        "run's end; each cell averages the log's records within 5 % of the frames, then the seeds, "
        "success in %:",
        "",
        markdown(header, rows),
        "",
        *_update_table(curves),
    ]


def _update_table(curves: Mapping[str, Sequence[Mapping]]) -> list[str]:
    """How PPO's updates went for each model whose runs PPO trained (their ``updates``): whether
    one moves its policy less per batch of experience, or fits its critic worse."""
    rows = []
    for model, per_seed in curves.items():
        stats = [curve["updates"] for curve in per_seed if "updates" in curve]
        if stats:
            mean = {key: float(np.mean([s[key] for s in stats])) for key in stats[0]}
            rows.append([model, f"{mean['approx_kl']:.4f}", f"{100 * mean['clip_fraction']:.1f}",
                         f"{mean['explained_variance']:.2f}"])  # fmt: skip
    if not rows:
        return []
    return [
        "How PPO's updates went, averaged over each run's log records, then its seeds: the approximate "
        "KL from the policy that acted to the updated one (how far an update moves it), the share of "
        "probability ratios clipped, in %, and the share of the returns' variance the critic explains:",
        "",
        markdown(["model", "approx. KL per update", "clipped", "explained variance"], rows),
        "",
    ]


def _frames(count: float) -> str:
    return f"{count / 1e3:,.0f}k" if count >= 10_000 else f"{count:,.0f}"


def mean_near(curve: Mapping[str, Sequence[float]], key: str, frames: float | None) -> float:
    """The mean of a training curve's ``key`` over its records within 5 % of ``frames`` (None: the
    run's last frames), or at the record nearest to them when none lies that close."""
    at = np.asarray(curve["frames"], dtype=float)
    values = np.asarray(curve[key], dtype=float)
    frames = at[-1] if frames is None else frames
    near = np.abs(at - frames) <= 0.05 * frames
    return float(values[near].mean() if near.any() else values[np.argmin(np.abs(at - frames))])


def _focus_differences(focus: str, records: list[dict]) -> list[str]:
    """Table 1's comparison of the focus model with each other model, if it has one."""
    key, columns = "focus_minus_model", main_metrics()
    rows = [
        [rec["model"], *(format_difference(c, rec[key][c]) for c in columns)] for rec in records if key in rec
    ]
    if not rows:
        return []
    header = ["model", *headers(columns, "Δ ")]
    return [
        f"{focus} minus each model, in points, with the 95 % interval of the difference over episodes "
        "(paired: the same episodes) and each model's training seeds:",
        "",
        markdown(header, rows),
        "",
    ]


def table2(experiment: str, record: Table2, out: Path, command: str) -> Rendered:
    """Rows: model x training room type; columns: SR / SPL on each test room type and overall."""
    rooms = record.setting.config.eval.rooms
    header = ["model", "trained on", *(f"{ROOM_NAMES[r]} SR / SPL" for r in rooms), "All SR / SPL"]
    rows = []
    for row in record.rows:
        cells = [_pair(row.record["rooms"].get(r)) for r in rooms]
        rows.append(
            [row.model, f"{ROOM_ABBREV[row.train_room]}-single", *cells, _pair(row.record["estimates"])]
        )
    lines = _header(
        record.setting, "Table 2: generalisation across room types (train on one, test on all)", command
    )
    lines += [markdown(header, rows), ""]
    return _payload(experiment, record.setting, runs=[row.record for row in record.rows]), lines


def _pair(estimates: dict | None) -> str:
    """``SR [95 % interval] / SPL`` of one cell (the SPL interval is left to the JSON, for width)."""
    if not estimates:
        return "–"
    return f"{format_estimate('success', estimates['success'])} / {format_estimate('spl', estimates['spl'], False)}"


def table3(experiment: str, record: Table3, out: Path, command: str) -> Rendered:
    records, rooms = record.models, record.setting.config.eval.rooms
    header = ["model", *(f"{ROOM_NAMES[r]} SR / SPL" for r in rooms), "All SR / SPL"]
    rows = [
        [rec["model"], *(_pair(rec["rooms"].get(r)) for r in rooms), _pair(rec["estimates"])]
        for rec in records
    ]
    lines = _header(record.setting, "Table 3: ablation of the hierarchical relationships", command)
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
    return _payload(experiment, record.setting, models=records), lines


def _ablation_cells(minus_full: dict, room: str) -> list[str]:
    return [format_difference(c, minus_full[part][c]) for part in ("all", room) for c in ("success", "spl")]


def ablation(experiment: str, record: Ablation, out: Path, command: str) -> Rendered:
    records, focus = record.models, record.setting.config.focus
    lines = _header(
        record.setting, f"Ablation: what each part of {focus} and of its recipe is worth", command
    )
    compared = compared_metrics()
    differences = [
        [rec["row"], rec["what"], *(format_difference(c, rec["minus_focus"][c]) for c in compared)]
        for rec in records
        if "minus_focus" in rec
    ]
    lines += [
        model_table(records),
        "",
        f"Each row minus {focus}, in points, with the 95 % interval of the difference over episodes "
        f"(paired: the same episodes, and {focus}'s seeds of the same numbers):",
        "",
        markdown(["row", "change", *headers(compared, "Δ ")], differences),
        "",
    ]
    for rec in records:
        if "same_actions" in rec:
            shares = ", ".join(f"{100 * share:.1f} %" for share in rec["same_actions"])
            lines += [
                f"Row {rec['row']} acts exactly as {focus} (the same snapshots and action draws, "
                f"every action equal) in {shares} of the episodes (per seed): how much test-time "
                "adaptation changes what the agent does.",
                "",
            ]
    lines += _validation_curves(records, out / f"{experiment}_validation.png")
    lines += training_curves(records, out / f"{experiment}_training.png")
    lines += ["Secondary metrics (mean over seeds):", "", details_table(records), ""]
    return _payload(experiment, record.setting, models=records), lines


def figure3(experiment: str, record: Figure3, out: Path, command: str) -> Rendered:
    from mapless.evaluate.figures import exploration_figure

    # The figure's Table 1 (its models, its runs) beside it, in table1/.
    write_report("table1", record.table1, out / "table1", command)
    pooled = {m: [r for seed in per_seed for r in seed] for m, per_seed in record.table1.results.items()}
    curves = exploration_figure(pooled, out / "figure3_exploration.png")
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
            [[m, format_estimate("exploration_ratio", e)] for m, e in record.final_ratio.items()],
        ),
        "",
    ]
    payload = {
        "experiment": experiment,
        "curves": curves,
        "final_ratio": {m: e.to_dict() for m, e in record.final_ratio.items()},
    }
    return payload, lines


def figures45(experiment: str, record: Figures45, out: Path, command: str) -> Rendered:
    from mapless.evaluate.figures import trajectory_figure, trajectory_gif

    write_report("table1", record.table1, out / "table1", command)
    library = record.scenes.build()
    focus, gif = record.focus, record.table1.setting.config.gif
    lines = ["# Figures 4 and 5: trajectories", "", f"Command: `{command}`.", ""]
    figures = {}
    for figure in record.figures:
        name, caption = figure.name, figure.caption
        if figure.index is None:
            lines += [f"No episode for {name} ({caption}) in this run.", ""]
            continue
        episode, parents = figure.results[focus], figure.parents
        trajectory_figure(figure.results, library, out / f"{name}.png", parents=parents)
        figures[name] = {"index": figure.index, "episode_id": episode.episode_id, "scene": episode.scene, "target": episode.target,
                         "parents": list(parents), "outcomes": {m: {"success": r.success, "length": r.length} for m, r in figure.results.items()}}  # fmt: skip
        lines += [f"## {name}: {caption}", "", f"{episode.scene}, target {episode.target}, parents {', '.join(parents) or '–'}.", "",
                  f"![{name}]({name}.png)", ""]  # fmt: skip
        if gif and name == "figure4_trajectories":
            trajectory_gif(episode, library, out / f"{name}_{focus}.gif")
            lines += [f"Egocentric views of {focus}: `{name}_{focus}.gif`.", ""]
    return {"experiment": experiment, "figures": figures}, lines


def layout_shift(experiment: str, record: LayoutShift, out: Path, command: str) -> Rendered:
    """A row per model, training arrangements and test set; then the paired differences."""
    config = record.setting.config
    shift = config.eval.shift_file or config.eval.shift_layouts
    lines = _header(record.setting, "Layout shift: the test floor plans under other arrangements", command)
    lines += [
        f"Shifted set: {record.shifted_episodes} episodes on the test floor plans under `{shift}`; "
        f"variant training: `env.layouts` = {config.variant_layouts}.",
        "Selection on val under the default arrangements.",
        "",
        model_table(record.models, label=("model", "trained on", "tested on")),
        "",
        "Trained on variants minus trained on default arrangements, in points, paired over the same "
        "episodes (and seeds):",
        "",
        _comparison_table(record.variants_minus_default),
        "",
        f"{config.focus} minus each model, on the default and on the shifted test set (paired): does its "
        "advantage grow or vanish when objects move?",
        "",
        _comparison_table(record.focus_minus_model),
        "",
    ]
    payload = _payload(
        experiment,
        record.setting,
        models=record.models,
        variants_minus_default=record.variants_minus_default,
        focus_minus_model=record.focus_minus_model,
    )
    return payload, lines


def _comparison_table(comparisons: list[dict]) -> str:
    """One row per ``{"comparison", "test_on", **difference_record}``: its paired differences."""
    if not comparisons:
        return "(none)"
    columns = main_metrics()
    header = ["comparison", "tested on", *headers(columns, "Δ ")]
    rows = [
        [d["comparison"], d["test_on"], *(format_difference(c, d[c]) for c in columns)] for d in comparisons
    ]
    return markdown(header, rows)


RENDERERS: dict[type, Callable[..., Rendered]] = {
    Table1: table1,
    Table2: table2,
    Table3: table3,
    Figure3: figure3,
    Figures45: figures45,
    LayoutShift: layout_shift,
    Ablation: ablation,
}
