"""The published levels Table 1's rows are set beside: the shipped file, which figures a row
reaches, bad entries, and where the report shows them (the reference protocol only)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapless.errors import MaplessError
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.published import _level, published_levels
from mapless.evaluate.report import model_record
from mapless.experiments import render
from mapless.experiments.config import ExperimentConfig, ExperimentEval
from mapless.experiments.records import Setting, Table1

DATA = Path(__file__).parent / "data"


def test_the_shipped_levels_are_the_references_figures() -> None:
    levels = published_levels()
    assert set(levels) == {"a3c", "sp", "savn", "spatt", "mjolnir_o", "mjolnir_r", "cvmeta"}
    assert levels["savn"].figures == {"success": 40.86, "spl": 16.15, "l5_success": 28.70, "l5_spl": 13.91}
    # The paper gives its model's L≥5 row only: the ALL figures are absent, not zero.
    assert levels["cvmeta"].figures == {"l5_success": 61.92, "l5_spl": 24.2}
    assert levels["cvmeta"].pair("all") == "–" and levels["cvmeta"].pair("l5") == "61.9 / 24.2"
    assert levels["mjolnir_o"].pair("all") == "65.3 / 21.1"


def test_a_row_reaches_the_figures_its_means_pass() -> None:
    sp = published_levels()["sp"]  # 35.13 / 15.47, L≥5 22.25 / 11.37
    means = {"success": 0.3513, "spl": 0.15, "l5_success": 0.30, "l5_spl": 0.1136}
    assert sp.reached(means) == ["success", "l5_success"]  # equal passes; 15.0 < 15.47; 11.36 < 11.37
    cvmeta = published_levels()["cvmeta"]
    assert cvmeta.reached({"success": 0.0, "spl": 0.0, "l5_success": 0.62, "l5_spl": 0.20}) == ["l5_success"]


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"all": [40.0, 16.0]}, "keys must be"),  # no source
        ({"all": [40.0, 16.0], "l10": [1, 2], "source": "x"}, "keys must be"),
        ({"all": [40.0], "source": "x"}, r"expected \[SR, SPL\] in %"),
        ({"l5": [0.41, 140.0], "source": "x"}, r"expected \[SR, SPL\] in %"),
        ({"l5": ["41", 14.0], "source": "x"}, r"expected \[SR, SPL\] in %"),
    ],
)
def test_a_bad_entry_is_refused_by_name(entry: dict, message: str) -> None:
    with pytest.raises(MaplessError, match=message):
        _level("savn", entry)


def _table1(protocol: str) -> tuple[dict, str]:
    raw = json.loads((DATA / "report_episodes.json").read_text())
    results = {
        m: [[EpisodeResult.from_dict(d) for d in seed] for seed in raw[m]]
        for m in ("random", "a3c", "cvmeta")
    }
    records = [
        model_record(m, per_seed, {"runs": []}, keep_episodes=False) for m, per_seed in results.items()
    ]
    config = ExperimentConfig(
        experiment="table1", budget="small", seeds=2, eval=ExperimentEval(protocol=protocol)
    )
    record = Table1(Setting(config, protocol, 24), records, results)
    payload, lines = render.table1("table1", record, Path("unused"), "cmd")
    return payload, "\n".join(lines)


def test_a_reference_report_sets_each_row_beside_its_published_level(monkeypatch) -> None:
    monkeypatch.setattr(render, "_validation_curves", lambda records, path: [])
    monkeypatch.setattr(render, "training_curves", lambda records, path: [])
    payload, text = _table1("reference")
    beside = {row["model"]: row for row in payload["published"]}
    assert set(beside) == {"a3c", "cvmeta"}  # random has no published level
    a3c = next(r for r in payload["models"] if r["model"] == "a3c")
    means = {k: a3c["estimates"][k]["mean"] for k in ("success", "spl", "l5_success", "l5_spl")}
    assert beside["a3c"]["means"] == means and beside["a3c"]["seeds"] == 2
    expected = [k for k, level in published_levels()["a3c"].figures.items() if means[k] * 100 >= level]
    assert beside["a3c"]["reached"] == expected
    cvmeta_row = next(line for line in text.splitlines() if line.startswith("| cvmeta | 2 |"))
    assert "| – |" in cvmeta_row and "| 61.9 / 24.2 |" in cvmeta_row
    assert "mapless/data/published_levels.yaml" in text
    # The standard protocol's 1.0 m rule is not the references': no published column.
    payload, text = _table1("standard")
    assert "published" not in payload and "published level" not in text
