"""Honest uncertainty: mean ± std over training seeds, and a 95 % bootstrap interval over episodes.

Every seed of a model is evaluated on the same fixed episode set, so per-episode values line up
across seeds. The interval resamples *episodes* (jointly across seeds: an episode drawn once counts
for every seed), applying the metric to each resample and averaging over seeds, which is the
uncertainty due to the finite episode set. The std over seeds is the training-run spread that SAVN's
README reports (5 runs). Percentile bootstrap, 2,000 resamples, seeded, so tables are reproducible.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from mapless.evaluate.metrics import EpisodeResult, episode_values

N_BOOTSTRAP = 2000
CONFIDENCE = 0.95

#: Metrics that get an interval: name -> (per-episode column, restrict to the L>=5 bucket).
CI_METRICS: dict[str, tuple[str, bool]] = {
    "success": ("success", False),
    "spl": ("spl", False),
    "l5_success": ("success", True),
    "l5_spl": ("spl", True),
    "ep_length": ("ep_length", False),
    "done_rate": ("done", False),
    "exploration_ratio": ("exploration", False),
}


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
    """Estimates of the :data:`CI_METRICS` from the results of several seeds on one episode set.

    Episodes are matched by ``index`` across seeds; a seed whose episode list differs is an error
    (it would make the joint resampling meaningless).
    """
    if not per_seed:
        raise ValueError("seed_estimates needs at least one seed's results")
    ordered = [sorted(results, key=lambda r: r.index) for results in per_seed]
    keys = [r.index for r in ordered[0]]
    for results in ordered[1:]:
        if [r.index for r in results] != keys:
            raise ValueError("all seeds must be evaluated on the same episodes")
    columns = [episode_values(results) for results in ordered]
    out: dict[str, Estimate] = {}
    for name, (column, l5_only) in CI_METRICS.items():
        mask = columns[0]["l5"] if l5_only else np.ones(len(keys), dtype=bool)
        if column == "exploration":
            # An episode stored without its poses has no known ratio: left out, as aggregate() and
            # the exploration curve leave it out (counted as 0 it would pull the estimate down).
            mask = mask & np.all([np.isfinite(c[column]) for c in columns], axis=0)
        matrix = np.stack([c[column][mask] for c in columns])
        per_seed_values = matrix.mean(axis=1) if matrix.shape[1] else np.full(len(columns), np.nan)
        mean, std = mean_std(per_seed_values)
        low, high = bootstrap_ci(matrix, seed=seed)
        out[name] = Estimate(mean, std, low, high, seeds=len(columns), episodes=int(mask.sum()))
    return out
