"""Per-episode records and the metrics of the paper and of the SAVN/MJOLNIR evaluation code.

Conventions (docs/guide/evaluation.md):

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
from typing import Literal, NamedTuple

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
    #: The step after which a target instance was first visible under the success rule (0: from
    #: the start), -1 if never: whether the agent's search found the target, whatever its stop did.
    #: None where not recorded (results cached before 2026-12-06 that nothing has filled in since).
    first_seen: int | None = None
    #: A target instance was in the frame, at any distance, where the episode ended (None: not
    #: recorded). With a failed ``Done``: the agent stopped short of the success rule's reach.
    ended_in_frame: bool | None = None
    #: Steps the agent took where a ``Done`` would have succeeded (a target instance visible under
    #: the success rule) and did something else: stops it passed up (None: not recorded).
    stops_passed: int | None = None

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


def same_actions(a: Sequence[EpisodeResult], b: Sequence[EpisodeResult]) -> int:
    """How many of the same episodes two agents played with exactly the same actions (under the
    evaluator's shared per-episode action draws: how far apart their policies are)."""
    return sum(x.actions == y.actions for x, y in zip(a, b, strict=True))


class Sighting(NamedTuple):
    """What a trajectory shows of its target (the :class:`EpisodeResult` fields of the same names)."""

    first_seen: int
    ended_in_frame: bool
    stops_passed: int


def sightings(
    goal_mask: np.ndarray,
    frame_mask: np.ndarray,
    start_pose: int,
    poses: Sequence[int],
    success: bool = False,
) -> Sighting:
    """A trajectory's :class:`Sighting`: the first step index at which the agent stood on a pose of
    ``goal_mask`` (bool ``[P]``: a target instance visible), 0 being the start, -1 if it never did;
    whether its last pose is one of ``frame_mask`` (a target instance in the frame at any distance);
    and the actions it took on a ``goal_mask`` pose other than a successful ``Done`` (action ``i``
    is taken at the pose before it: the start, then ``poses[i - 1]``)."""
    path = np.concatenate([[start_pose], np.asarray(poses, dtype=np.int64)]).astype(np.int64)
    on_goal = goal_mask[path]
    hits = np.flatnonzero(on_goal)
    acted_on_goal = int(on_goal[: len(poses)].sum())
    return Sighting(
        int(hits[0]) if len(hits) else -1, bool(frame_mask[path[-1]]), acted_on_goal - int(success)
    )


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
    target instance visible), failed-action share, exploration, seen, approach (a success's actions
    from its first sight of the target on, Done included), stops passed, short done (a false done
    with a target instance in the frame); the last four NaN where not recorded or, for approach, not
    a success."""
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
        "seen": np.fromiter(
            (np.nan if r.first_seen is None else float(r.first_seen >= 0) for r in results),
            dtype=np.float64,
            count=n,
        ),
        "approach": np.fromiter(
            (
                r.length - r.first_seen
                if r.success and r.first_seen is not None and r.first_seen >= 0
                else np.nan
                for r in results
            ),
            dtype=np.float64,
            count=n,
        ),
        "stops_passed": np.fromiter(
            (np.nan if r.stops_passed is None else float(r.stops_passed) for r in results),
            dtype=np.float64,
            count=n,
        ),
        "short_done": np.fromiter(
            (
                np.nan
                if r.ended_in_frame is None
                else float(r.called_done and not r.success and r.ended_in_frame)
                for r in results
            ),
            dtype=np.float64,
            count=n,
        ),
    }
    return values


@dataclass(frozen=True)
class Metric:
    """One aggregate metric, declared once (as habitat-lab registers a ``Measure``): what it is
    computed from and how every report shows it. Aggregates, seed estimates, the ``mapless eval``
    and ``mapless compare`` tables and the experiment reports all read these declarations.

    name: its key in aggregates, estimates and the JSON reports.
    label: its column header in the markdown tables.
    column: the per-episode value it is taken over (a key of :func:`episode_values`).
    l5_only: over the L>=5 bucket only (SAVN's ``GreaterThan/5``: bucket means over bucket members).
    per: a ratio of sums over the whole set, ``sum(column) / sum(per)``, instead of a mean over
        episodes (so long episodes weigh by their length); such a metric has no interval.
    percent: shown in percent (rates); else as is (lengths).
    interval: gets seed estimates with a bootstrap interval (:mod:`mapless.evaluate.stats`).
    table: ``"main"`` (the main table: SR, SPL and their L>=5 forms), ``"details"`` (the secondary
        table, mean over seeds) or None (JSON only).
    compared: ``mapless compare`` and the ablation report show its B − A difference.
    """

    name: str
    label: str
    column: str
    l5_only: bool = False
    per: str | None = None
    percent: bool = True
    interval: bool = True
    table: Literal["main", "details"] | None = None
    compared: bool = False

    def __post_init__(self) -> None:
        if self.per is not None and self.interval:
            raise ValueError(f"metric {self.name!r}: a ratio of sums has no bootstrap interval")
        if self.compared and not self.interval:  # a paired difference is bootstrapped as an interval is
            raise ValueError(f"metric {self.name!r}: compared, so it needs an interval")

    @property
    def scale(self) -> float:
        """Factor from the stored fraction to the shown number."""
        return 100.0 if self.percent else 1.0

    def aggregate(self, values: dict[str, np.ndarray]) -> float:
        """The metric over a set, from its :func:`episode_values`."""
        if self.per is not None:
            return float(values[self.column].sum() / max(values[self.per].sum(), 1.0))
        chosen = values[self.column][self.episodes(values)]
        return float(chosen.mean()) if len(chosen) else float("nan")

    def episodes(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """Mask of the episodes the metric is taken over: the L>=5 bucket for ``l5_only``, and only
        those with a known value (an episode without stored poses has no exploration ratio: 0
        would pull the mean down)."""
        column = values[self.column]
        mask = values["l5"] if self.l5_only else np.ones(len(column), dtype=bool)
        return mask & np.isfinite(column)


#: Every metric by name, in table order (that of the JSON reports' keys too).
METRICS: dict[str, Metric] = {}


def register(metric: Metric) -> Metric:
    """Declare a metric (its per-episode ``column`` must be one :func:`episode_values` computes)."""
    if metric.name in METRICS:
        raise ValueError(f"metric {metric.name!r} is declared twice")
    METRICS[metric.name] = metric
    return metric


register(Metric("success", "SR", "success", table="main", compared=True))
register(Metric("spl", "SPL", "spl", table="main", compared=True))
register(Metric("l5_success", "SR L≥5", "success", l5_only=True, table="main", compared=True))
register(Metric("l5_spl", "SPL L≥5", "spl", l5_only=True, table="main", compared=True))
register(Metric("ep_length", "length", "ep_length", percent=False, table="details"))
register(Metric("done_rate", "Done", "done", table="details"))
register(Metric("false_done_rate", "false Done", "false_done", table="details", compared=True))
register(
    Metric("failed_action_rate", "failed", "failed_actions", per="ep_length", interval=False, table="details")
)
register(Metric("exploration_ratio", "explore", "exploration", table="details"))
#: The SR an oracle stop would give (Done at the first sight of the target): SR against it splits a
#: model's failures into search (never saw the target) and stopping (saw it, did not end there).
register(Metric("seen_rate", "seen", "seen", table="details", compared=True))
#: The false Dones that had the target in the frame, out of the rule's reach: a judgement of distance.
register(Metric("short_done_rate", "short Done", "short_done", table="details", compared=True))
#: How a success ends: the actions from its first sight of the target to its Done. With the steps
#: before it (length − approach), it splits a success's path, hence SPL, into search and approach.
register(Metric("approach_steps", "approach", "approach", percent=False, table="details", compared=True))
#: Where a success's approach goes, and what a failure missed: the steps on which ``Done`` would
#: have succeeded and the agent did something else (per episode, over every episode).
register(Metric("stops_passed", "passed", "stops_passed", percent=False, table="details", compared=True))
register(Metric("reward", "reward", "reward", percent=False, interval=False))


def main_metrics() -> tuple[str, ...]:
    """The main table's columns: SR, SPL, and both over the L>=5 bucket."""
    return tuple(name for name, m in METRICS.items() if m.table == "main")


def detail_metrics() -> tuple[str, ...]:
    """The secondary table's columns."""
    return tuple(name for name, m in METRICS.items() if m.table == "details")


def compared_metrics() -> tuple[str, ...]:
    """What ``mapless compare`` and the ablation report show as B − A."""
    return tuple(name for name, m in METRICS.items() if m.compared)


def interval_metrics() -> tuple[Metric, ...]:
    """The metrics with seed estimates and a bootstrap interval."""
    return tuple(m for m in METRICS.values() if m.interval)


def aggregate(results: Sequence[EpisodeResult]) -> dict[str, float]:
    """Every metric of a list of episodes (fractions, not percent), as :data:`METRICS` declares it.

    ``failed_action_rate`` is failed actions / all actions over the whole set (a ratio of sums, so
    long episodes weigh by their length); ``exploration_ratio`` is the per-episode final ratio,
    averaged over episodes.
    """
    if not results:
        return {"episodes": 0, "l5_episodes": 0, **{k: float("nan") for k in METRICS}}
    v = episode_values(results)
    return {
        "episodes": len(results),
        "l5_episodes": int(v["l5"].sum()),
        **{name: metric.aggregate(v) for name, metric in METRICS.items()},
    }


def summarize(results: Sequence[EpisodeResult]) -> dict[str, dict[str, float]]:
    """``{"overall": metrics, room_type: metrics, ...}`` for the room types present."""
    out = {"overall": aggregate(results)}
    for room in ROOM_TYPES:
        subset = [r for r in results if r.room_type == room]
        if subset:
            out[room] = aggregate(subset)
    return out
