"""The published levels of Table 1's models (``mapless/data/published_levels.yaml``), and which of
them a measured row reaches. The references measured them on their own episodes under the 1.5 m
rule, so only a reference-protocol report sets its rows beside them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources

import yaml

from mapless.errors import MaplessError

LEVELS_FILE = "published_levels.yaml"

#: The main table's metrics each published pair fills: (SR, SPL) on all episodes and on L≥5.
PAIRS = {"all": ("success", "spl"), "l5": ("l5_success", "l5_spl")}


@dataclass(frozen=True)
class PublishedLevel:
    """One model's published figures, in %, by metric name (a figure not found is absent)."""

    model: str
    figures: Mapping[str, float]
    source: str

    def pair(self, subset: str) -> str:
        """``"35.1 / 15.5"``, the published SR / SPL on ``subset`` (``all`` or ``l5``), or ``–``."""
        sr, spl = PAIRS[subset]
        if sr not in self.figures:
            return "–"
        return f"{self.figures[sr]:.1f} / {self.figures[spl]:.1f}"

    def reached(self, means: Mapping[str, float]) -> list[str]:
        """The published figures that ``means`` (by metric name, fractions as the estimates hold
        them) reaches, by metric name, in the main table's order."""
        return [name for name, level in self.figures.items() if means[name] * 100.0 >= level]


@cache
def published_levels() -> dict[str, PublishedLevel]:
    """Every published level the package ships, by registered model name."""
    raw = yaml.safe_load(resources.files("mapless.data").joinpath(LEVELS_FILE).read_text())
    return {model: _level(model, entry) for model, entry in raw.items()}


def _level(model: str, entry: dict) -> PublishedLevel:
    unknown = set(entry) - {*PAIRS, "source"}
    if unknown or "source" not in entry:
        raise MaplessError(
            f"{LEVELS_FILE}, {model}: keys must be {sorted(PAIRS)} and 'source', got {sorted(entry)}"
        )
    figures = {}
    for subset, names in PAIRS.items():
        pair = entry.get(subset)
        if pair is None:
            continue
        if len(pair) != len(names) or not all(isinstance(v, int | float) and 0 <= v <= 100 for v in pair):
            raise MaplessError(f"{LEVELS_FILE}, {model}.{subset}: expected [SR, SPL] in %, got {pair!r}")
        figures.update(zip(names, map(float, pair), strict=True))
    # Keep the main table's column order whatever the file's order.
    order = [name for names in PAIRS.values() for name in names]
    return PublishedLevel(model, {k: figures[k] for k in order if k in figures}, str(entry["source"]))
