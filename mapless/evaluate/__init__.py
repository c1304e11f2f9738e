"""Evaluation: metrics (SR, SPL, L>=5, Done and failed-action rates, ratio of exploration), the
batched parallel runner, checkpoint selection, statistics over seeds and episodes, reports and
figures. See docs/guide/evaluation.md."""

from mapless.evaluate.metrics import EpisodeResult, aggregate, spl, summarize
from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate

__all__ = [
    "AgentSpec",
    "EpisodeResult",
    "EvalSettings",
    "LibrarySpec",
    "aggregate",
    "evaluate",
    "spl",
    "summarize",
]
