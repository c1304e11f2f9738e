"""Per-episode records and the metrics of the paper and of the SAVN/MJOLNIR evaluation code.

Conventions (docs/evaluation.md):

* ``length`` L counts every action the agent took, failed moves and the final ``Done`` included
  (SAVN's ``eps_len``); ``optimal_length`` L* is the stored shortest-path length including ``Done``
  (SAVN's ``len(path)``).
* SPL = S · L* / max(L, L*) (the paper's formula). SAVN divides by L without the clamp; on a
  graph-consistent simulator L >= L* on every success, so both agree (a test checks it).
* The ``L>=5`` bucket holds the episodes with L* >= 5. An episode with unknown L* (-1, no path) is
  in both buckets with SPL 0, as SAVN counts its ``best = inf`` episodes.
* Ratio of exploration at step t = distinct poses among the poses after actions 1..t, divided by t
  (the paper: "two states explored in the first five steps is 40 %"). The start pose is not an
  explored state; a failed move or ``Done`` revisits the current pose and adds none.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from mapless.scenes.catalogue import ROOM_TYPES

L5_THRESHOLD = 5


@dataclass(frozen=True)
class EpisodeResult:
    """What happened in one evaluation episode (everything a metric or a figure needs)."""

    index: int  # position in the evaluated episode list
    episode_id: str
    scene: str
    room_type: str
    target: str
    success: bool
    length: int
    optimal_length: int
    called_done: bool
    failed_actions: int
    reward: float
    start_pose: int
    #: Pose id (scene-local) after each action; ``len(poses) == length``.
    poses: tuple[int, ...] = field(default=(), repr=False)
    actions: tuple[int, ...] = field(default=(), repr=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["poses"] = list(self.poses)
        d["actions"] = list(self.actions)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeResult:
        d = dict(d)
        d["poses"] = tuple(int(p) for p in d.get("poses", ()))
        d["actions"] = tuple(int(a) for a in d.get("actions", ()))
        return cls(**d)


def spl(success: bool, length: int, optimal_length: int) -> float:
    """S · L* / max(L, L*); 0 on failure or when L* is unknown."""
    if not success or optimal_length <= 0:
        return 0.0
    return optimal_length / max(length, optimal_length)


def in_l5(optimal_length: int) -> bool:
    """Member of SAVN's ``GreaterThan/5`` bucket (unknown L* counts, as SAVN's ``inf``)."""
    return optimal_length < 0 or optimal_length >= L5_THRESHOLD


def exploration_counts(poses: Sequence[int]) -> np.ndarray:
    """``[L]``: number of distinct poses among the poses after actions 1..t, for t = 1..L."""
    seen: set[int] = set()
    counts = np.empty(len(poses), dtype=np.int64)
    for t, pose in enumerate(poses):
        seen.add(int(pose))
        counts[t] = len(seen)
    return counts


def exploration_ratio(poses: Sequence[int]) -> np.ndarray:
    """``[L]``: the ratio of exploration after each step (distinct explored states / steps)."""
    return exploration_counts(poses) / np.arange(1, len(poses) + 1)


def exploration_curve(
    results: Iterable[EpisodeResult], horizon: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mean ratio of exploration per step index over the episodes still running at that step.

    Returns ``(mean[t], count[t])`` for t = 1..horizon (index 0 is step 1); ``count`` is how many
    episodes lasted at least t steps (the mean is NaN where it is 0). Averaging only over running
    episodes keeps a curve from being pulled by episodes that already stopped.
    """
    ratios = [exploration_ratio(r.poses) for r in results if r.poses]
    horizon = horizon or max((len(r) for r in ratios), default=0)
    total = np.zeros(horizon)
    count = np.zeros(horizon, dtype=np.int64)
    for r in ratios:
        n = min(len(r), horizon)
        total[:n] += r[:n]
        count[:n] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean, count


def episode_values(results: Sequence[EpisodeResult]) -> dict[str, np.ndarray]:
    """Per-episode arrays: success, spl, l5 membership, length, done, false done (``Done`` with no
    target instance visible), failed-action share, exploration."""
    n = len(results)
    values = {
        "success": np.fromiter((r.success for r in results), dtype=np.float64, count=n),
        "spl": np.fromiter(
            (spl(r.success, r.length, r.optimal_length) for r in results), dtype=np.float64, count=n
        ),
        "l5": np.fromiter((in_l5(r.optimal_length) for r in results), dtype=bool, count=n),
        "ep_length": np.fromiter((r.length for r in results), dtype=np.float64, count=n),
        "done": np.fromiter((r.called_done for r in results), dtype=np.float64, count=n),
        "false_done": np.fromiter(
            (r.called_done and not r.success for r in results), dtype=np.float64, count=n
        ),
        "failed_actions": np.fromiter((r.failed_actions for r in results), dtype=np.float64, count=n),
        "reward": np.fromiter((r.reward for r in results), dtype=np.float64, count=n),
        "exploration": np.fromiter(
            (exploration_counts(r.poses)[-1] / len(r.poses) if r.poses else np.nan for r in results),
            dtype=np.float64,
            count=n,
        ),
    }
    return values


#: Aggregate metric keys in table order; ``l5_*`` are over the L>=5 bucket only (SAVN's
#: ``GreaterThan/5``: bucket means over bucket members).
METRIC_KEYS = (
    "success",
    "spl",
    "l5_success",
    "l5_spl",
    "ep_length",
    "done_rate",
    "false_done_rate",
    "failed_action_rate",
    "exploration_ratio",
    "reward",
)


def aggregate(results: Sequence[EpisodeResult]) -> dict[str, float]:
    """Mean metrics of a list of episodes (fractions, not percent).

    ``failed_action_rate`` is failed actions / all actions over the whole set (a ratio of sums, so
    long episodes weigh by their length); ``exploration_ratio`` is the per-episode final ratio,
    averaged over episodes.
    """
    if not results:
        return {"episodes": 0, "l5_episodes": 0, **{k: float("nan") for k in METRIC_KEYS}}
    v = episode_values(results)
    l5 = v["l5"]
    mean_or_nan = lambda a: float(a.mean()) if len(a) else float("nan")  # noqa: E731
    return {
        "episodes": len(results),
        "l5_episodes": int(l5.sum()),
        "success": mean_or_nan(v["success"]),
        "spl": mean_or_nan(v["spl"]),
        "l5_success": mean_or_nan(v["success"][l5]),
        "l5_spl": mean_or_nan(v["spl"][l5]),
        "ep_length": mean_or_nan(v["ep_length"]),
        "done_rate": mean_or_nan(v["done"]),
        "false_done_rate": mean_or_nan(v["false_done"]),
        "failed_action_rate": float(v["failed_actions"].sum() / max(v["ep_length"].sum(), 1.0)),
        "exploration_ratio": mean_or_nan(v["exploration"][np.isfinite(v["exploration"])]),
        "reward": mean_or_nan(v["reward"]),
    }


def summarize(results: Sequence[EpisodeResult]) -> dict[str, dict[str, float]]:
    """``{"overall": metrics, room_type: metrics, ...}`` for the room types present."""
    out = {"overall": aggregate(results)}
    for room in ROOM_TYPES:
        subset = [r for r in results if r.room_type == room]
        if subset:
            out[room] = aggregate(subset)
    return out
