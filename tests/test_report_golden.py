"""Every report text and JSON number made from fixed episode results, held against a capture.

``tests/data/report_episodes.json`` holds five models' episodes (two seeds, 24 episodes over the
four room types, some without poses, some with unknown optimal length). Everything that turns
results into numbers and text (aggregates, seed estimates, bootstrap intervals, paired differences,
the tables of ``mapless eval`` and ``mapless compare``, every experiment renderer) is rendered from
them and compared, character for character, with ``report_expected.md`` and
``report_expected.json``. A change to a number, a label, a column order or a digit shows up here."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapless import provenance
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.report import (
    comparison_table,
    details_table,
    difference_record,
    model_record,
    model_table,
    room_table,
)
from mapless.evaluate.stats import difference_estimates, seed_estimates
from mapless.experiments import render
from mapless.experiments.config import ExperimentConfig
from mapless.experiments.records import (
    Ablation,
    Figure3,
    LayoutShift,
    Setting,
    Table1,
    Table2,
    Table2Row,
    Table3,
)

DATA = Path(__file__).parent / "data"
COMPARED = (
    *("success", "spl", "l5_success", "l5_spl"),
    *("false_done_rate", "seen_rate", "short_done_rate", "approach_steps", "stops_passed"),
)


def _episodes() -> dict[str, list[list[EpisodeResult]]]:
    raw = json.loads((DATA / "report_episodes.json").read_text())
    return {m: [[EpisodeResult.from_dict(d) for d in seed] for seed in seeds] for m, seeds in raw.items()}


def _rooms(per_seed: list[list[EpisodeResult]], room: str) -> list[list[EpisodeResult]]:
    return [[r for r in seed if r.room_type == room] for seed in per_seed]


def _render_all(out: Path) -> tuple[str, dict]:
    """Every table and record, as one markdown text and one JSON payload (the experiment configs
    left out of the payloads: they are not made from results)."""
    results = _episodes()
    models = ["random", "a3c", "savn", "cvmeta"]
    focus, ablated = "cvmeta", "cvmeta_no_meta"
    records = [model_record(m, results[m], {"runs": []}, keep_episodes=False) for m in models]
    for rec in records:
        if rec["model"] != focus:
            rec["focus_minus_model"] = difference_record(results[rec["model"]], results[focus])
    config = ExperimentConfig(experiment="table1", budget="small", seeds=2, focus=focus)
    setting = Setting(config, "standard protocol (fixture)", 24)
    text: list[str] = [
        model_table(records),
        model_table(records, interval=False),
        details_table(records),
        *(room_table(rec) for rec in records),
        comparison_table("a3c", results["a3c"], focus, results[focus]),
    ]
    payload: dict = {
        "records": records,  # their per_seed entries are summarize()'s, per room type too
        "difference_kitchen": difference_record(results["a3c"], results[focus], "kitchen"),
    }

    table2 = Table2(
        setting,
        [
            Table2Row(m, room, model_record(f"{m} {room}", _rooms(results[m], room), keep_episodes=False))
            for m in ("a3c", focus)
            for room in ("kitchen", "bedroom")
        ],
    )
    table3_records = [model_record(focus, results[focus], {"removed_room": None}, keep_episodes=False)]
    ablated_rec = model_record("Kitchen_no_relationships", results[ablated], {"removed_room": "kitchen"}, keep_episodes=False)  # fmt: skip
    ablated_rec["minus_full"] = {
        "all": difference_record(results[focus], results[ablated]),
        "kitchen": difference_record(results[focus], results[ablated], "kitchen"),
    }
    table3_records.append(ablated_rec)
    ablation_rec = model_record(f"{focus}: no meta", results[ablated], {"row": "no_meta", "what": "no meta"})
    # The ablation report's differences cover false Done too (mapless compare's metrics).
    compared = difference_estimates(results[focus], results[ablated], COMPARED)
    ablation_rec["minus_focus"] = {k: v.to_dict() for k, v in compared.items()}
    ablation_records = [model_record(focus, results[focus], {"row": "focus"}), ablation_rec]
    for rec in ablation_records:
        rec.pop("episodes")
    shifted = [
        model_record(f"{m} | {trained} | {test}", results[m if trained == "default" else ablated], keep_episodes=False)
        for m, trained, test in (("a3c", "default", "default"), (focus, "variants", "shifted"))
    ]  # fmt: skip
    comparisons = [
        {"comparison": "a3c variants − default", "test_on": t, **difference_record(results["a3c"], results[ablated])}
        for t in ("default", "shifted")
    ]  # fmt: skip
    rendered = {
        "table1": render.table1("table1", Table1(setting, records, {m: results[m] for m in models}), out, "cmd"),
        "table2": render.table2("table2", table2, out, "cmd"),
        "table3": render.table3("table3", Table3(setting, table3_records), out, "cmd"),
        "ablation": render.ablation("ablation", Ablation(setting, ablation_records), out, "cmd"),
        "layout_shift": render.layout_shift(
            "layout_shift", LayoutShift(setting, 24, shifted, comparisons, comparisons[:1]), out, "cmd"
        ),
        "figure3": render.figure3(
            "figure3",
            Figure3(Table1(setting, records, {}), {m: seed_estimates(results[m])["exploration_ratio"] for m in models}),
            out,
            "cmd",
        ),
    }  # fmt: skip
    for name, (rendered_payload, lines) in rendered.items():
        rendered_payload.pop("config", None)
        # Table 1's records are the ones above: named, not repeated.
        payload[name] = {k: "records" if v is records else v for k, v in rendered_payload.items()}
        text += [f"<!-- {name} -->", *lines]
    return "\n\n".join(text) + "\n", payload


def _dump(payload: dict) -> str:
    # repr of a float round-trips, so equal text is equal numbers, NaN included; keys stay in the
    # order the reports write them.
    return json.dumps(payload, indent=1, allow_nan=True) + "\n"


@pytest.fixture
def quiet_figures(monkeypatch):
    """No clock in the headers, no figure files and no nested Table 1 report: text and numbers only."""
    import mapless.evaluate.figures as figures

    monkeypatch.setattr(provenance.time, "strftime", lambda fmt, *a: "2026-01-01 00:00")
    monkeypatch.setattr(figures, "exploration_figure", lambda pooled, path: {"fixture": True})
    monkeypatch.setattr(render, "write_report", lambda *a, **k: None)


def test_reports_from_fixed_results_match_the_capture(tmp_path, quiet_figures):
    text, payload = _render_all(tmp_path)
    (tmp_path / "report.md").write_text(text)  # for a diff when they differ
    (tmp_path / "report.json").write_text(_dump(payload))
    assert text == (DATA / "report_expected.md").read_text(), tmp_path / "report.md"
    assert _dump(payload) == (DATA / "report_expected.json").read_text(), tmp_path / "report.json"
    # The capture holds what the reports are for: intervals, std over seeds and signed differences.
    assert "±" in text and "[" in text and "B − A" in text and "+" in text
