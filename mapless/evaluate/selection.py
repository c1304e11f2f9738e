"""Checkpoint selection under the evaluation protocols (mapless.episodes.protocols).

SAVN's ``full_eval.py``: evaluate every checkpoint of a run on the protocol's selection set, keep
the best by success rate (ties: SPL, then the earlier checkpoint), evaluate it once on the report
set and report that. Under the ``paper`` protocol (what the paper and MJOLNIR did) both are the
same episodes of x21-x30: the reported number is then a maximum over checkpoints on the test
episodes, an optimistic estimate; every report made with it says so.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mapless.checkpoint import FINAL_MODEL_FILE, load_file, mixed_runs, snapshots, training_clock
from mapless.episodes.protocols import get_protocol
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import episodes_digest
from mapless.evaluate.metrics import EpisodeResult, aggregate, main_metrics
from mapless.evaluate.report import read_json, write_json
from mapless.evaluate.runner import (
    AgentSpec,
    EvalRun,
    EvalSettings,
    LibrarySpec,
    evaluate,
    lacks_sightings,
    with_sightings,
)
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary


def cache_file(directory: Path, name: str, digest: str) -> Path:
    """Where ``directory`` caches one model file's results on the episodes of ``digest``
    (:func:`episodes_digest`): ``name`` (split and model file) plus the digest, so that sets sharing
    a split name (an ``eval.select_file`` override, a published file) keep a file each instead of
    overwriting one another. A file named before the digest (``name.json``) is still used where it
    holds these episodes, so paths to it (in docs, in reports) stay valid."""
    path = directory / f"{name}_{digest[:8]}.json"
    legacy = directory / f"{name}.json"
    if not path.exists() and legacy.is_file():
        try:
            key = read_json(legacy).get("key", {})
        except (OSError, ValueError):
            key = {}
        if key.get("episodes") == digest:
            return legacy
    return path


def candidates(run_dir: str | Path) -> list[tuple[int, Path]]:
    """``(training episodes, model file)`` of every snapshot of a run, plus its final model when it
    is not already a snapshot of the same episode count."""
    run_dir = Path(run_dir)
    found = snapshots(run_dir)
    final = run_dir / FINAL_MODEL_FILE
    if final.is_file():
        episodes = int(load_file(final).get("counters", {}).get("episodes", -1))
        if episodes not in {e for e, _ in found}:
            found.append((episodes, final))
    if not found:
        raise MaplessError(f"run folder {run_dir} holds no model snapshot or final model")
    mixed = mixed_runs([path for _, path in sorted(found)])
    if mixed is not None:
        raise MaplessError(mixed)
    return sorted(found)


def _training_progress(model_file: Path, clock: tuple[list[int], list[float]]) -> dict:
    """How far training had got at a snapshot: its frames and, from the run's log, its training
    minutes (None without a log that reaches it), for validation curves against frames and time."""
    frames = int(load_file(model_file).get("counters", {}).get("frames", -1))
    logged_frames, seconds = clock
    minutes = None
    if frames >= 0 and logged_frames and logged_frames[-1] >= frames:
        minutes = float(np.interp(frames, [0, *logged_frames], [0.0, *seconds])) / 60
    return {"frames": frames, "minutes": minutes}


def best_index(metrics: Sequence[dict]) -> int:
    """Highest success rate; ties broken by SPL, then by the earliest checkpoint."""
    return max(range(len(metrics)), key=lambda i: (metrics[i]["success"], metrics[i]["spl"], -i))


@dataclass
class Selection:
    protocol: str
    label: str
    chosen: str
    chosen_episodes: int
    scores: list[dict]  # per candidate: episodes, path, success, spl, l5_success, l5_spl
    report: EvalRun

    def summary(self) -> dict:
        return {
            "protocol": self.protocol,
            "protocol_label": self.label,
            "chosen": self.chosen,
            "chosen_episodes": self.chosen_episodes,
            "candidates": self.scores,
        }


def cached_evaluate(
    spec: AgentSpec,
    episodes: list[Episode],
    settings: EvalSettings,
    library: LibrarySpec,
    cache: Path | None,
) -> EvalRun:
    """Evaluate, reusing ``cache`` when it holds the same checkpoint, episodes and settings."""
    # Results do not depend on the worker count (tests/test_eval_runner.py), so it is not in the key.
    settings_key = {k: v for k, v in asdict(settings).items() if k != "workers"}
    spec_key = asdict(spec)
    if spec.adapt:  # added later: keyed only when off, so earlier caches still hit
        del spec_key["adapt"]
    if spec.inner_lr is None:  # likewise: keyed only when set
        del spec_key["inner_lr"]
    key = {"spec": spec_key, "episodes": episodes_digest(episodes), "settings": settings_key}
    if spec.checkpoint:  # a resumed run rewrites final_model.pt under the same name
        stat = Path(spec.checkpoint).stat()
        key["model_file"] = [stat.st_size, stat.st_mtime_ns]
    if cache is not None and cache.is_file():
        try:
            stored = read_json(cache)
        except (OSError, ValueError):  # unreadable (an older, non-atomic version wrote it): a miss
            stored = {}
        if stored.get("key") == json.loads(json.dumps(key)):
            results = [EpisodeResult.from_dict(d) for d in stored["episodes"]]
            if any(lacks_sightings(r) for r in results):  # cached before they were recorded
                results = with_sightings(results, episodes, _scenes(library))
                _store(cache, key, stored["seconds"], stored["steps"], results)
            return EvalRun(results, stored["seconds"], stored["steps"])
    run = evaluate(spec, episodes, settings, library)
    if cache is not None:
        _store(cache, key, run.seconds, run.steps, run.results)
    return run


@functools.lru_cache(maxsize=1)
def _scenes(library: LibrarySpec) -> SceneLibrary:
    """One library for the caches of one report: each run's caches fill their sightings from the
    same scenes, loaded once instead of once per cache file."""
    return library.build()


def _store(cache: Path, key: dict, seconds: float, steps: int, results: list[EpisodeResult]) -> None:
    write_json(
        {"key": key, "seconds": seconds, "steps": steps, "metrics": aggregate(results),
         "episodes": [r.to_dict() for r in results]},
        cache,
    )  # fmt: skip


def select_and_report(
    run_dir: str | Path,
    select_episodes: list[Episode],
    report_episodes: list[Episode] | None,
    settings: EvalSettings,
    library: LibrarySpec,
    protocol: str = "standard",
    progress: Callable[[str], None] | None = None,
    report_name: str | None = None,
    within_minutes: float | None = None,
) -> Selection:
    """Evaluate every candidate of ``run_dir`` on ``select_episodes``, pick the best, and evaluate it
    once on ``report_episodes`` (``paper`` protocol: reuse the selection run on the same episodes).
    ``report_name`` names report episodes that are not the protocol's built-in set (an episode file)
    in the label and the cache. ``within_minutes``: only the snapshots of the first N minutes of
    training (by the run's log), as if the run had stopped there. Per-checkpoint results are cached
    under ``run_dir/eval/``."""
    p = get_protocol(protocol)
    select_split, report_split, label = p.select_split, p.report_split, p.label
    if report_name and protocol == "paper":
        select_split = report_split = report_name
        label = f"PAPER PROTOCOL: selected and reported on the same episodes of {report_name} (optimistic)"
    elif report_name:
        report_split = report_name
        label = f"{protocol} protocol: selected on {p.select_split}, reported once on {report_name}; success within {p.visibility_distance} m"
    run_dir = Path(run_dir)
    scores, runs = [], []
    clock = training_clock(run_dir)
    found = [(episodes, path, _training_progress(path, clock)) for episodes, path in candidates(run_dir)]
    if within_minutes is not None:
        found = [c for c in found if c[2]["minutes"] is not None and c[2]["minutes"] <= within_minutes]
        if not found:
            raise MaplessError(
                f"run folder {run_dir} has no snapshot within its first {within_minutes:g} training "
                "minutes (or no training log that dates them)"
            )
        label = f"{label}; chosen among the snapshots of the first {within_minutes:g} training minutes"
    select_digest = episodes_digest(select_episodes)
    for episodes_done, path, progress_at in found:
        spec = AgentSpec(checkpoint=str(path))
        cache = cache_file(run_dir / "eval", f"{select_split}_{path.stem}", select_digest)
        run = cached_evaluate(spec, select_episodes, settings, library, cache)
        m = aggregate(run.results)
        scores.append(
            {
                "episodes": episodes_done,
                "path": str(path),
                **{k: m[k] for k in main_metrics()},
                **progress_at,
            }
        )
        runs.append(run)
        if progress:
            progress(f"  {path.name}: {select_split} SR {m['success']:.3f} SPL {m['spl']:.3f}")
    best = best_index(scores)
    chosen = scores[best]["path"]
    if p.select_split == p.report_split or report_episodes is None:
        report = runs[best]
    else:
        name = f"{report_split}_{Path(chosen).stem}"
        cache = cache_file(run_dir / "eval", name, episodes_digest(report_episodes))
        report = cached_evaluate(AgentSpec(checkpoint=chosen), report_episodes, settings, library, cache)
    return Selection(protocol, label, chosen, int(scores[best]["episodes"]), scores, report)


@dataclass
class RunEvaluation:
    """A trained run evaluated on the report episodes: the results of ``model_file``, chosen by
    ``selection`` when there was one, else the run's final model (or the model file given)."""

    report: EvalRun
    model_file: str
    selection: Selection | None = None


#: Why selection takes no test-time setting: it compares checkpoints as they were trained.
SELECTION_AS_TRAINED = (
    "selection scores each checkpoint as trained; --no-adapt and --inner-lr evaluate one model file "
    "(or a run's final model) without --select"
)


def evaluate_run(
    path: str | Path,
    report_episodes: list[Episode],
    settings: EvalSettings,
    library: LibrarySpec,
    select_episodes: list[Episode] | None = None,
    protocol: str = "standard",
    progress: Callable[[str], None] | None = None,
    report_name: str | None = None,
    within_minutes: float | None = None,
    adapt: bool = True,
    inner_lr: float | None = None,
) -> RunEvaluation:
    """How a trained run is evaluated, for ``mapless eval`` and the experiments alike. With
    ``select_episodes``: every checkpoint of the run folder ``path`` on them, the best once on
    ``report_episodes`` (:func:`select_and_report`; ``within_minutes``: among the snapshots of the
    first N training minutes). Without: the run's final model, or the model file ``path``, on
    ``report_episodes``, adapted at test time or not (``adapt``) at ``inner_lr`` if given
    (:class:`~mapless.evaluate.runner.AgentSpec`); selection scores checkpoints as they were trained."""
    if select_episodes is not None and (not adapt or inner_lr is not None):
        raise MaplessError(SELECTION_AS_TRAINED)
    if select_episodes is not None:
        sel = select_and_report(
            path, select_episodes, report_episodes, settings, library, protocol, progress, report_name,
            within_minutes,
        )  # fmt: skip
        return RunEvaluation(sel.report, sel.chosen, sel)
    from mapless.checkpoint import resolve_model_file

    model_file = str(resolve_model_file(path))
    spec = AgentSpec(checkpoint=model_file, adapt=adapt, inner_lr=inner_lr)
    return RunEvaluation(evaluate(spec, report_episodes, settings, library), model_file)
