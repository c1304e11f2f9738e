"""Honest uncertainty: mean ± std over training seeds, and a 95 % bootstrap interval over episodes.

Every seed of a model is evaluated on the same fixed episode set, so per-episode values line up
across seeds. The interval resamples *episodes* (jointly across seeds: an episode drawn once counts
for every seed), applying the metric to each resample and averaging over seeds, which is the
uncertainty due to the finite episode set. The std over seeds is the training-run spread that SAVN's
README reports (5 runs). Percentile bootstrap, 2,000 resamples, seeded, so tables are reproducible.

Two models on the same episode set are compared by :func:`difference_estimates`: the difference of
their means over seeds, with an interval whose resamples draw episodes (shared by the two models:
a paired comparison) and, independently for each model, its seeds. Seed-to-seed spread is the larger
source of uncertainty at small budgets, so an interval over episodes alone would overstate what a
difference shows; with two or three seeds the seeds' part is itself rough (too narrow, if anything).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from mapless.evaluate.metrics import (
    METRICS,
    EpisodeResult,
    Metric,
    episode_values,
    interval_metrics,
    main_metrics,
)

N_BOOTSTRAP = 2000
CONFIDENCE = 0.95


@dataclass(frozen=True)
class Estimate:
    """A metric over seeds: mean and sample std of the per-seed values, and the episode bootstrap CI."""

    mean: float
    std: float
    ci_low: float
    ci_high: float
    seeds: int
    episodes: int

    def to_dict(self) -> dict:
        return asdict(self)


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1; 0 for one value)."""
    a = np.asarray(values, dtype=np.float64)
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else 0.0


def bootstrap_ci(
    matrix: np.ndarray, n_boot: int = N_BOOTSTRAP, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[float, float]:
    """Percentile interval of the mean of ``matrix [seeds, episodes]`` under resampling of episodes.

    Resampling is shared across seeds (column indices), because the seeds ran the same episodes.
    """
    matrix = np.atleast_2d(np.asarray(matrix, dtype=np.float64))
    n = matrix.shape[1]
    if n == 0:
        return float("nan"), float("nan")
    per_episode = matrix.mean(axis=0)  # the mean over seeds commutes with resampling columns
    rng = np.random.default_rng(seed)
    means = np.empty(n_boot)
    # Chunks bound memory for large sets (1000 episodes x 2000 resamples would be 16 MB at once).
    chunk = max(1, 2_000_000 // n)
    for start in range(0, n_boot, chunk):
        stop = min(n_boot, start + chunk)
        idx = rng.integers(0, n, size=(stop - start, n))
        means[start:stop] = per_episode[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    return float(np.quantile(means, alpha)), float(np.quantile(means, 1.0 - alpha))


def seed_estimates(per_seed: Sequence[Sequence[EpisodeResult]], seed: int = 0) -> dict[str, Estimate]:
    """Estimates of the metrics declared with an interval (:data:`~mapless.evaluate.metrics.METRICS`)
    from the results of several seeds on one episode set.

    Episodes are matched by ``index`` across seeds; a seed whose episode list differs is an error
    (it would make the joint resampling meaningless).
    """
    _, columns = _aligned_columns(per_seed)
    out: dict[str, Estimate] = {}
    for metric in interval_metrics():
        mask = _metric_mask(metric, columns)
        matrix = np.stack([c[metric.column][mask] for c in columns])
        per_seed_values = matrix.mean(axis=1) if matrix.shape[1] else np.full(len(columns), np.nan)
        mean, std = mean_std(per_seed_values)
        low, high = bootstrap_ci(matrix, seed=seed)
        out[metric.name] = Estimate(mean, std, low, high, seeds=len(columns), episodes=int(mask.sum()))
    return out


@dataclass(frozen=True)
class Difference:
    """``B - A`` of a metric: the difference of the two models' means over seeds, and its 95 %
    bootstrap interval over episodes (paired) and each model's seeds."""

    mean: float
    ci_low: float
    ci_high: float
    seeds_a: int
    seeds_b: int
    episodes: int

    def to_dict(self) -> dict:
        return asdict(self)


def difference_estimates(
    per_seed_a: Sequence[Sequence[EpisodeResult]],
    per_seed_b: Sequence[Sequence[EpisodeResult]],
    metrics: Sequence[str] | None = None,
    seed: int = 0,
) -> dict[str, Difference]:
    """Model B minus model A on the same episode set (matched by ``index``; other sets are an error),
    for ``metrics`` (names of metrics with an interval; None: the main table's)."""
    keys, columns_a = _aligned_columns(per_seed_a)
    keys_b, columns_b = _aligned_columns(per_seed_b)
    if keys_b != keys:
        raise ValueError("both models must be evaluated on the same episodes")
    out: dict[str, Difference] = {}
    for name in main_metrics() if metrics is None else metrics:
        metric = METRICS[name]
        if not metric.interval:
            raise ValueError(f"metric {name!r} has no bootstrap interval, so no paired difference")
        mask = _metric_mask(metric, [*columns_a, *columns_b])
        a = np.stack([c[metric.column][mask] for c in columns_a])
        b = np.stack([c[metric.column][mask] for c in columns_b])
        if not mask.any():
            out[name] = Difference(float("nan"), float("nan"), float("nan"), len(a), len(b), 0)
            continue
        # Each metric draws the same resamples (as bootstrap_ci does), whatever the others are.
        resampled = _paired_seed_bootstrap(a, b, np.random.default_rng(seed))
        alpha = (1.0 - CONFIDENCE) / 2.0
        low, high = np.quantile(resampled, [alpha, 1.0 - alpha])
        diff = float(b.mean() - a.mean())  # every seed has the same episodes: mean of seed means
        out[name] = Difference(diff, float(low), float(high), len(a), len(b), int(mask.sum()))
    return out


def _paired_seed_bootstrap(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``N_BOOTSTRAP`` resampled values of ``mean(b) - mean(a)`` (``[seeds, episodes]`` each): each
    resample draws the episodes once for both models, and each model's seeds with replacement."""
    n = a.shape[1]
    out = np.empty(N_BOOTSTRAP)
    chunk = max(1, 2_000_000 // n)  # bounds the [resamples, episodes] arrays, as bootstrap_ci does
    for start in range(0, N_BOOTSTRAP, chunk):
        k = min(N_BOOTSTRAP, start + chunk) - start
        weights_a = rng.multinomial(len(a), np.full(len(a), 1.0 / len(a)), size=k) / len(a)
        weights_b = rng.multinomial(len(b), np.full(len(b), 1.0 / len(b)), size=k) / len(b)
        per_episode = weights_b @ b - weights_a @ a  # [k, episodes]: each resample's seed mix
        episodes = rng.integers(0, n, size=(k, n))
        out[start : start + k] = np.take_along_axis(per_episode, episodes, axis=1).mean(axis=1)
    return out


def _aligned_columns(
    per_seed: Sequence[Sequence[EpisodeResult]],
) -> tuple[list[int], list[dict[str, np.ndarray]]]:
    """Episode indices and each seed's per-episode arrays, in index order; the seeds must agree."""
    if not per_seed:
        raise ValueError("estimates need at least one seed's results")
    ordered = [sorted(results, key=lambda r: r.index) for results in per_seed]
    keys = [r.index for r in ordered[0]]
    for results in ordered[1:]:
        if [r.index for r in results] != keys:
            raise ValueError("all seeds must be evaluated on the same episodes")
    return keys, [episode_values(results) for results in ordered]


def _metric_mask(metric: Metric, columns: Sequence[dict[str, np.ndarray]]) -> np.ndarray:
    """The episodes a metric is taken over (:meth:`~mapless.evaluate.metrics.Metric.episodes`) in
    every seed: the seeds ran the same episodes, so the first seed's L>=5 bucket is theirs, and an
    episode counts only where every seed has its value (an exploration ratio needs stored poses)."""
    known = np.all([np.isfinite(c[metric.column]) for c in columns], axis=0)
    return metric.episodes(columns[0]) & known
