"""Errors a user can act on: every message names the bad value and the valid choices."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class MaplessError(Exception):
    """Base class of errors caused by bad input (names, configs, files); the CLI prints them cleanly."""


class UnknownNameError(MaplessError, KeyError):
    def __init__(self, kind: str, name: str, valid: Iterable[str], summary: str | None = None):
        valid = list(valid)
        close = difflib.get_close_matches(str(name), valid, n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        shown = summary or ", ".join(valid[:60]) + (" ..." if len(valid) > 60 else "") or "none"
        super().__init__(f"unknown {kind} {name!r}.{hint} Valid choices: {shown}")
        self.kind, self.name, self.valid = kind, name, valid

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class TrainingDiverged(MaplessError):
    """A loss or gradient became NaN or infinite: the run stops before the step would reach the
    parameters, and the last checkpoint on disk stays the last good state."""
