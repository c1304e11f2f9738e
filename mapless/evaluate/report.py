"""Evaluation reports: JSON records and markdown tables.

Rates (SR, SPL, Done, failed actions, exploration) are shown in percent, as the papers do; episode
length in steps. A cell is ``mean`` for one seed and ``mean ± std`` over seeds, followed by the 95 %
bootstrap interval over episodes in brackets (mapless.evaluate.stats). A difference between two
models is a signed ``+6.3 [+2.1, +10.5]``, in points for rates, its interval over episodes and seeds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from mapless.errors import MaplessError
from mapless.evaluate.metrics import (
    METRICS,
    EpisodeResult,
    compared_metrics,
    detail_metrics,
    main_metrics,
    same_actions,
    summarize,
)
from mapless.evaluate.stats import Difference, Estimate, difference_estimates, seed_estimates
from mapless.files import write_text
from mapless.scenes.catalogue import ROOM_TYPES

ROOM_NAMES = {
    "kitchen": "Kitchen",
    "living_room": "Living room",
    "bedroom": "Bedroom",
    "bathroom": "Bathroom",
}


def format_estimate(key: str, estimate: Estimate | dict, interval: bool = True) -> str:
    """``61.9 ± 1.2 [58.4, 65.0]`` (± only with several seeds)."""
    e = estimate if isinstance(estimate, dict) else estimate.to_dict()
    if e["mean"] is None or math.isnan(e["mean"]):
        return "–"
    s = METRICS[key].scale
    digits = 1
    text = f"{e['mean'] * s:.{digits}f}"
    if e["seeds"] > 1:
        text += f" ± {e['std'] * s:.{digits}f}"
    if interval and not math.isnan(e["ci_low"]):
        text += f" [{e['ci_low'] * s:.{digits}f}, {e['ci_high'] * s:.{digits}f}]"
    return text


def format_difference(key: str, difference: Difference | dict) -> str:
    """``-7.0 [-11.2, -2.9]``: a signed difference and its 95 % interval (points for rates)."""
    d = difference if isinstance(difference, dict) else difference.to_dict()
    if d["mean"] is None or math.isnan(d["mean"]):
        return "–"
    s = METRICS[key].scale
    return f"{d['mean'] * s:+.1f} [{d['ci_low'] * s:+.1f}, {d['ci_high'] * s:+.1f}]"


def difference_record(
    per_seed_a: Sequence[Sequence[EpisodeResult]],
    per_seed_b: Sequence[Sequence[EpisodeResult]],
    room: str | None = None,
    metrics: Sequence[str] | None = None,
) -> dict[str, dict]:
    """JSON-able :func:`~mapless.evaluate.stats.difference_estimates` of B minus A, over all
    episodes or those of one room type, for ``metrics`` (None: the main table's)."""
    if room is not None:
        per_seed_a, per_seed_b = room_results(per_seed_a, room), room_results(per_seed_b, room)
    differences = difference_estimates(per_seed_a, per_seed_b, metrics)
    return {k: v.to_dict() for k, v in differences.items()}


def room_results(per_seed: Sequence[Sequence[EpisodeResult]], room: str) -> list[list[EpisodeResult]]:
    """Each seed's results on the episodes of one room type."""
    return [[r for r in results if r.room_type == room] for results in per_seed]


def format_value(key: str, value: float) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value * METRICS[key].scale:.1f}"


def markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def model_record(
    label: str,
    per_seed: Sequence[Sequence[EpisodeResult]],
    meta: dict | None = None,
    keep_episodes: bool = True,
) -> dict:
    """JSON-able record of one model on one episode set: estimates over seeds, per-seed summaries
    (overall and per room type) and, optionally, every episode of every seed."""
    estimates = seed_estimates(per_seed)
    record = {
        "model": label,
        **(meta or {}),
        "seeds": len(per_seed),
        "estimates": {k: v.to_dict() for k, v in estimates.items()},
        "per_seed": [summarize(results) for results in per_seed],
        "rooms": _room_estimates(per_seed),
    }
    if keep_episodes:
        record["episodes"] = [[r.to_dict() for r in results] for results in per_seed]
    return record


def _room_estimates(per_seed: Sequence[Sequence[EpisodeResult]]) -> dict[str, dict]:
    out = {}
    for room in ROOM_TYPES:
        subsets = room_results(per_seed, room)
        if subsets and all(subsets):
            out[room] = {k: v.to_dict() for k, v in seed_estimates(subsets).items()}
    return out


def model_table(
    records: Sequence[dict],
    columns: Sequence[str] | None = None,
    interval: bool = True,
    label: Sequence[str] = ("model",),
) -> str:
    """One row per model record (``model_record``), one column per metric (None: the main table's).
    A record labelled in parts, ``"a3c | variants | shifted"``, fills the ``label`` columns one part
    each (a markdown row with more cells than its header loses the extra ones, so the parts must
    match ``label``)."""
    columns = main_metrics() if columns is None else columns
    header = [*label, *headers(columns)]
    rows = []
    for rec in records:
        parts = rec["model"].split(" | ")
        if len(parts) != len(label):
            raise ValueError(
                f"model label {rec['model']!r} has {len(parts)} parts, the table {len(label)}: {list(label)}"
            )
        rows.append([*parts, *(_cell(rec["estimates"], c, interval) for c in columns)])
    return markdown(header, rows)


def _cell(estimates: dict, key: str, interval: bool) -> str:
    return format_estimate(key, estimates[key], interval) if key in estimates else "–"


def headers(metrics: Sequence[str], prefix: str = "") -> list[str]:
    """The metrics' column headers (``prefix="Δ "``: those of their differences)."""
    return [f"{prefix}{METRICS[name].label}" for name in metrics]


def room_table(record: dict, columns: Sequence[str] | None = None) -> str:
    """Per-room-type breakdown of one model record, plus the overall row (None: the main columns)."""
    columns = main_metrics() if columns is None else columns
    header = ["room type", *headers(columns)]
    rows = [
        [ROOM_NAMES[room], *(_cell(est, c, False) for c in columns)] for room, est in record["rooms"].items()
    ]
    rows.append(["All", *(_cell(record["estimates"], c, False) for c in columns)])
    return markdown(header, rows)


def details_table(records: Sequence[dict]) -> str:
    """Secondary metrics (mean over seeds, overall): length, Done, false Done, failed actions,
    exploration."""
    cols = detail_metrics()
    header = ["model", *headers(cols)]
    rows = []
    for rec in records:
        per_seed = [s["overall"] for s in rec["per_seed"]]
        rows.append(
            [rec["model"], *(format_value(c, sum(s[c] for s in per_seed) / len(per_seed)) for c in cols)]
        )
    return markdown(header, rows)


def read_results(spec: str | Path) -> tuple[str, list[list[EpisodeResult]]]:
    """Every seed's episodes of one result file, and a label: ``FILE`` is an evaluation's cache
    (``RUN/eval/*.json``: one seed) or a model record (``mapless eval``'s ``SPLIT.json``: its
    seeds); ``FILE:MODEL`` picks a model's record from an experiment report (``table1.json``)."""
    return results_of(*result_record(spec))


def result_record(spec: str | Path) -> tuple[Path, dict]:
    """The file and the one model's record that ``spec`` names (as :func:`read_results` reads it):
    an evaluation's cache, a model record, or ``FILE:MODEL``'s record of an experiment report."""
    text = str(spec)
    path, model = Path(text), None
    if not path.is_file() and ":" in text:
        head, _, model = text.rpartition(":")
        path = Path(head)
    try:
        data = read_json(path)
    except (OSError, ValueError) as error:
        raise MaplessError(f"cannot read results {path}: {error}") from None
    if not isinstance(data, dict):
        raise MaplessError(f"{path}: not a mapless result file (a JSON object with 'episodes')")
    if "models" in data:
        names = [r.get("model") for r in data["models"]]
        if model not in names:
            raise MaplessError(
                f"{path} is an experiment report: name one of its models as {path}:MODEL ({', '.join(map(str, names))})"
            )
        data = data["models"][names.index(model)]
    elif model is not None:
        raise MaplessError(f"{path} holds one model's results; leave out ':{model}'")
    return path, data


def results_of(path: Path, data: dict) -> tuple[str, list[list[EpisodeResult]]]:
    """A label and every seed's episodes of the record ``data`` of the file ``path``."""
    episodes = data.get("episodes")
    if not isinstance(episodes, list) or not episodes:
        raise MaplessError(f"{path}: no 'episodes' (a mapless evaluation, `mapless eval` record or report)")
    per_seed = episodes if isinstance(episodes[0], list) else [episodes]
    try:
        results = [[EpisodeResult.from_dict(d) for d in seed] for seed in per_seed]
    except (TypeError, ValueError) as error:
        raise MaplessError(f"{path}: malformed episode record ({error})") from None
    # An evaluation cache is named after its checkpoint; its run folder says more.
    label = data.get("model") or (path.parent.parent.name if path.parent.name == "eval" else path.stem)
    return str(label), results


def comparison_table(
    label_a: str,
    per_seed_a: Sequence[Sequence[EpisodeResult]],
    label_b: str,
    per_seed_b: Sequence[Sequence[EpisodeResult]],
) -> str:
    """A, B and B minus A, paired over the same episodes (an error otherwise), for the metrics
    declared ``compared``."""
    compared = compared_metrics()
    try:
        differences = difference_estimates(per_seed_a, per_seed_b, compared)
        a, b = seed_estimates(per_seed_a), seed_estimates(per_seed_b)
    except ValueError as error:  # different episode sets
        raise MaplessError(f"cannot compare {label_a} with {label_b}: {error}") from None
    rows = [
        [
            METRICS[k].label,
            format_estimate(k, a[k]),
            format_estimate(k, b[k]),
            format_difference(k, differences[k]),
        ]
        for k in compared
    ]
    table = markdown(["metric", f"A: {label_a}", f"B: {label_b}", "B − A"], rows)
    seeds = list(zip(per_seed_a, per_seed_b, strict=False))  # the seeds both sides have, as paired above
    if not all(x.actions and y.actions for a, b in seeds for x, y in zip(a, b, strict=True)):
        return table  # results recorded without their actions
    same, episodes = sum(same_actions(a, b) for a, b in seeds), sum(len(a) for a, _ in seeds)
    # Under the same action draws (the evaluator's per-episode uniforms), equal actions mean policies
    # too close to part: e.g. a model adapted at test time against its unadapted θ_0.
    share = f"{same} of {episodes} episodes ({100 * same / episodes:.1f} %)"
    return f"{table}\n\nA and B took exactly the same actions in {share}."


def write_report_files(payload: dict, text: str, stem: Path) -> tuple[dict, str]:
    """Write a report as ``<stem>.json`` and ``<stem>.md``, each with the provenance of the code and
    machine that made it (:mod:`mapless.provenance`); returns the two as written."""
    from mapless.provenance import describe, provenance

    record = provenance()
    payload = {**payload, "provenance": record}
    text = f"{text.rstrip()}\n\nMade by {describe(record)}.\n"
    write_json(payload, stem.parent / f"{stem.name}.json")
    write_text(stem.parent / f"{stem.name}.md", text)
    return payload, text


def write_json(payload: dict, path: Path) -> None:
    write_text(path, json.dumps(payload, indent=1, allow_nan=True))


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())
