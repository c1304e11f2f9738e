"""Published evaluation episode pickles (SAVN, MJOLNIR, HOZ): read them and map them onto the
built-in scenes (writing ours in their format: :mod:`mapless.offline.episode_writer`).

Reading needs none of the original classes and never runs the file's code
(:mod:`mapless.safe_pickle`): SAVN pickles hold a ``ThorAgentState`` start state and torch
GloVe tensors.

Mapping (docs/guide/interop.md, section 2): AI2-THOR object ids changed between versions, so a target id
is matched verbatim when the built-in scene has it, else to the nearest object of the same type (v1
names translated) within a horizontal radius, else, when the episode lists one instance of the type
and the built-in scene has one, to that one (the object moved); an id with no counterpart is
dropped when the episode keeps other targets. The start becomes the nearest built-in pose with the
same yaw and horizon, within a grid step, from which a target instance can be seen. Episodes that
cannot be mapped are listed with the reason (one of :data:`SKIP_CAUSES`) and skipped.
"""

from __future__ import annotations

import collections
import gzip
import math
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapless.errors import MaplessError
from mapless.offline.format import (
    OfflineFormatError,
    object_type_of_id,
    parse_pose_key,
)
from mapless.safe_pickle import Placeholder, load_untrusted
from mapless.sim.episode import Episode
from mapless.sim.scene_data import SceneData, pose_key

#: v1/SAVN type names -> AI2-THOR 5 types whose instances stand for them when mapping targets.
TYPE_ALIASES: dict[str, tuple[str, ...]] = {
    "CoffeeMaker": ("CoffeeMachine",),
    "Lamp": ("DeskLamp", "FloorLamp"),
    "TableTop": ("DiningTable", "CoffeeTable"),
    "NightStand": ("SideTable",),
    "Glassbottle": ("Bottle",),
    "ToiletPaperRoll": ("ToiletPaper",),
}
DEFAULT_MAX_TARGET_DISTANCE = 0.5  # m, horizontal; 96 % of HOZ targets lie within 0.3 m
DEFAULT_MAX_START_DISTANCE = 0.36  # m: one diagonal grid step


@dataclass(frozen=True)
class RawEpisode:
    """One episode of a published pickle, as stored (scene and ids in the file's spelling)."""

    index: int
    scene: str
    target_type: str
    target_ids: tuple[str, ...]
    start: tuple[float, float, int, int]  # x, z, yaw, horizon
    room: str | None = None
    embedding: np.ndarray | None = field(default=None, repr=False, compare=False)


def _start_of(state: Any) -> tuple[float, float, int, int]:
    if isinstance(state, str):
        return parse_pose_key(state)
    values = state if isinstance(state, dict) else getattr(state, "__dict__", {})
    try:
        numbers = [values[k] for k in ("x", "z", "rotation", "horizon")]
        if not all(isinstance(v, int | float | np.number) for v in numbers):
            raise TypeError
        x, z, rotation, horizon = (float(v) for v in numbers)
        if not (np.isfinite(x) and np.isfinite(z)):  # round() keeps a NaN, which maps anywhere
            raise ValueError
        return round(x, 2), round(z, 2), round(rotation), round(horizon)
    except (KeyError, TypeError, ValueError, OverflowError):  # round() of inf or NaN included
        shown = state if isinstance(state, Placeholder | str) else type(state).__name__
        raise ValueError(f"start state {shown!r} has no finite x, z, rotation, horizon") from None


def _as_array(value: Any) -> np.ndarray | None:
    if value is None:
        return None
    import torch

    try:
        if isinstance(value, torch.Tensor):
            # Through the class, not the instance: a tensor's pickled state may set attributes on it.
            value = torch.Tensor.detach(value).cpu().to(torch.float64).numpy()
        return np.asarray(value, dtype=np.float64)
    except (
        TypeError,
        ValueError,
        RuntimeError,
        OverflowError,
    ):  # not numbers, ragged, huge, a dtype numpy lacks
        return None


def read_episode_file(path: str | Path) -> tuple[list[RawEpisode], list[tuple[int, str]]]:
    """Episodes of a SAVN/MJOLNIR/HOZ pickle, and ``(index, reason)`` of entries that are malformed."""
    path = Path(path)
    if not path.is_file():
        raise OfflineFormatError(path, "no such episode file")
    try:
        raw = path.read_bytes()
        if raw[:2] == b"\x1f\x8b":  # gzipped, as the package ships the published files
            raw = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as error:  # BadGzipFile is an OSError
        raise OfflineFormatError(path, f"cannot be read ({error})") from None
    try:
        data = load_untrusted(raw)
    except Exception as error:  # whatever the allowed constructors raise on crafted arguments
        raise OfflineFormatError(
            path, f"not a readable episode pickle ({type(error).__name__}: {str(error)[:200]})"
        ) from None
    if not isinstance(data, list | tuple):
        raise OfflineFormatError(path, f"expected a list of episode dicts, found {type(data).__name__}")
    episodes: list[RawEpisode] = []
    bad: list[tuple[int, str]] = []
    for i, entry in enumerate(data):
        if not isinstance(entry, dict):
            bad.append((i, f"entry is a {type(entry).__name__}, not a dict"))
            continue
        missing = [k for k in ("scene", "goal_object_type", "task_data", "state") if k not in entry]
        if missing:
            bad.append((i, f"entry has no {', '.join(missing)}"))
            continue
        try:
            start = _start_of(entry["state"])
        except ValueError as error:
            bad.append((i, str(error)))
            continue
        not_text = [k for k in ("scene", "goal_object_type") if not isinstance(entry[k], str)]
        if not_text or not isinstance(entry.get("room"), str | None):
            bad.append((i, f"entry's {', '.join(not_text) or 'room'} is not a string"))
            continue
        task = entry["task_data"]
        ids = (task,) if isinstance(task, str) else task if isinstance(task, list | tuple) else None
        if task is not None and (ids is None or not all(isinstance(t, str) for t in ids)):
            bad.append((i, f"task_data is not an object id or a list of object ids ({type(task).__name__})"))
            continue
        episodes.append(
            RawEpisode(
                index=i,
                scene=entry["scene"],
                target_type=entry["goal_object_type"],
                target_ids=tuple(ids or ()),
                start=start,
                room=entry.get("room"),
                embedding=_as_array(entry.get("glove_embedding")),
            )
        )
    return episodes, bad


# ---------------------------------------------------------------------------------------- mapping

#: Why an episode is skipped: each reason starts with one of these, then ": details". The reader's
#: reasons for malformed entries (``read_episode_file``) come on top.
SKIP_CAUSES = (
    "unknown scene",
    "no target",
    "target id without a position",
    "no object of that type in the scene",
    "no object of that type nearby",
    "start yaw not on the grid",
    "start pose not reachable",
    "target visible from no pose",
    "target not reachable from the start",
)


@dataclass
class MappingReport:
    """Mapped episodes (``episode_id`` = ``<prefix>/<room>/<index in the file>``) and the skipped
    ones as ``(index in the file, reason)``.

    Target ids: ``exact_ids`` kept verbatim, ``nearest_ids`` matched to the nearest object of the
    type within the radius, ``moved_ids`` matched to the scene's only instance of the type farther
    away, ``dropped_ids`` without a counterpart in an episode that kept its other targets.
    ``exact_episodes``: every target id and the start verbatim, the published episode itself, its
    type agreeing with its ids. ``contradictions``: ``(index in the file, detail)`` of the mapped
    episodes whose ``goal_object_type`` names none of their target ids' types; the ids decide (they
    are what success is judged by), and such an episode is never exact."""

    episodes: list[Episode]
    skipped: list[tuple[int, str]]
    total: int
    exact_ids: int = 0
    nearest_ids: int = 0
    moved_ids: int = 0
    dropped_ids: int = 0
    snapped_starts: int = 0
    exact_episodes: int = 0
    contradictions: list[tuple[int, str]] = field(default_factory=list)

    @property
    def mapped(self) -> int:
        return len(self.episodes)

    def causes(self) -> collections.Counter:
        """Skipped episodes per cause (the reason up to its first colon)."""
        return collections.Counter(_reason_kind(r) for _, r in self.skipped)

    def summary(self, max_reasons: int = 10) -> str:
        share = f" ({self.mapped / self.total:.1%} mapped)" if self.total else ""
        lines = [
            f"{self.mapped} of {self.total} episodes mapped, {len(self.skipped)} skipped{share}; "
            f"{self.exact_episodes} exact (target ids and start verbatim)",
            f"target ids: {self.exact_ids} matched verbatim, {self.nearest_ids} by type + nearest position, "
            f"{self.moved_ids} to the scene's only instance of the type (moved), {self.dropped_ids} dropped "
            "(no counterpart; the episode kept its other targets)",
            f"start poses: {self.snapped_starts} snapped to the nearest built-in pose",
        ]
        if self.contradictions:
            index, detail = self.contradictions[0]
            lines.append(
                f"type contradicts ids: {len(self.contradictions)} episode(s) name a goal type none of "
                f"their target ids has; mapped by their ids, not exact (e.g. #{index}: {detail})"
            )
        for reason, count in self.causes().most_common(max_reasons):
            example = next(f"#{i}: {r}" for i, r in self.skipped if _reason_kind(r) == reason)
            lines.append(f"  skipped {count}: {reason} (e.g. {example})")
        return "\n".join(lines)


def mapping_table(reports: dict[str, MappingReport]) -> str:
    """Markdown table of several mapping reports (one row each, e.g. per file): mapped share,
    exact episodes, how the targets matched, and the skipped episodes per cause."""
    causes = [c for c in dict.fromkeys(c for r in reports.values() for c in r.causes()) if c]
    header = [
        "set",
        "episodes",
        "mapped",
        "exact",
        "ids nearest",
        "ids moved",
        "ids dropped",
        "starts snapped",
    ]
    rows = [
        "| " + " | ".join([*header, *(f"skipped: {c}" for c in causes)]) + " |",
        "|" + "---|" * (len(header) + len(causes)),
    ]
    for label, r in reports.items():
        share = f"{r.mapped} ({r.mapped / r.total:.1%})" if r.total else "0"
        counts = r.causes()
        cells = [label, r.total, share, r.exact_episodes, r.nearest_ids, r.moved_ids, r.dropped_ids]
        cells += [r.snapped_starts, *(counts.get(c, 0) for c in causes)]
        rows.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(rows)


def _reason_kind(reason: str) -> str:
    return reason.split(":", 1)[0]


def _id_type_and_position(object_id: str) -> tuple[str, tuple[float, float, float]]:
    """THOR ids are ``Type|x|y|z`` (+ ``|ChildType`` for sub-objects such as ``SinkBasin``)."""
    parts = object_id.split("|")
    if len(parts) < 4:
        raise ValueError(object_id)
    return object_type_of_id(object_id), (float(parts[1]), float(parts[2]), float(parts[3]))


def _v5_types(object_type: str) -> tuple[str, ...]:
    return (object_type, *TYPE_ALIASES.get(object_type, ()))


def map_episodes(
    episodes: Iterable[RawEpisode],
    *,
    scene_data: Callable[[str], SceneData] | None = None,
    max_target_distance: float = DEFAULT_MAX_TARGET_DISTANCE,
    max_start_distance: float = DEFAULT_MAX_START_DISTANCE,
    rotation_step: int = 45,
    id_prefix: str = "import",
) -> MappingReport:
    """Map published episodes onto the built-in scenes.

    ``scene_data(name)`` supplies the built-in SceneData: the start then becomes the nearest pose
    within ``max_start_distance`` with the same yaw and horizon from which a target instance can
    be seen (the published start itself where it can), and the optimal length is computed.
    Without it starts snap to the scene's reachable grid (``load_scene(name).reachable``), yaw and
    horizon unchanged, and the optimal length is unknown (-1).
    """
    from mapless.scenes import load_scene
    from mapless.scenes.catalogue import canonical_scene

    report = MappingReport(episodes=[], skipped=[], total=0)
    distances: dict[tuple[str, tuple[str, ...]], np.ndarray] = {}  # episodes share targets
    for episode in episodes:
        report.total += 1
        try:
            name = canonical_scene(episode.scene)
        except MaplessError:
            report.skipped.append((episode.index, f"unknown scene: {episode.scene!r}"))
            continue
        scene = load_scene(name)
        match = _map_targets(scene, episode.target_ids, max_target_distance)
        if match.problem:
            report.skipped.append((episode.index, match.problem))
            continue
        x, z, yaw, horizon = episode.start
        if yaw % rotation_step:
            report.skipped.append(
                (episode.index, f"start yaw not on the grid: {yaw} is no multiple of {rotation_step} degrees")
            )
            continue
        yaw %= 360
        optimal = -1
        if scene_data is None:
            start, snapped = _snap_to_grid(scene, x, z, yaw, horizon, max_start_distance)
        else:
            sd = scene_data(name)
            key = (name, tuple(match.ids))
            if key not in distances:
                known = [sd.instance_ids.index(i) for i in match.ids if i in sd.instance_ids]
                distances[key] = sd.distances_to(sd.goal_mask_for_instances(np.array(known, dtype=np.int64)))
            to_goal = distances[key]
            if not (to_goal == 0).any():
                why = _never_visible(scene, sd, match.ids)
                report.skipped.append(
                    (episode.index, f"target visible from no pose: {match.ids} in {name}, {why}")
                )
                continue
            start, snapped, distance = _start_pose(sd, x, z, yaw, horizon, to_goal, max_start_distance)
            if start is not None and distance < 0:
                report.skipped.append(
                    (
                        episode.index,
                        f"target not reachable from the start: {match.ids} from {pose_key(*start)} in {name} "
                        "(no pose within reach sees it: another part of the pose graph)",
                    )
                )
                continue
            optimal = distance + 1
        if start is None:
            report.skipped.append(
                (episode.index, f"start pose not reachable: {pose_key(x, z, yaw, horizon)} in {name}")
            )
            continue
        target_types = [scene.object(i).type for i in match.ids]
        goal = next((t for t in _v5_types(episode.target_type) if t in target_types), None)
        published = [object_type_of_id(i) for i in episode.target_ids]
        agrees = goal is not None and any(t in published for t in _v5_types(episode.target_type))
        if not agrees:
            report.contradictions.append(
                (
                    episode.index,
                    f"goal_object_type {episode.target_type!r}, target ids {list(episode.target_ids)}",
                )
            )
            goal = goal or target_types[0]
        report.exact_ids += match.exact
        report.nearest_ids += match.nearest
        report.moved_ids += match.moved
        report.dropped_ids += match.dropped
        report.snapped_starts += snapped
        report.exact_episodes += agrees and not snapped and match.exact == len(episode.target_ids)
        report.episodes.append(
            Episode(
                scene=name,
                target=goal,
                start=start,
                optimal_length=optimal,
                target_ids=tuple(match.ids),
                episode_id=f"{id_prefix}/{scene.room_type}/{episode.index:04d}",
            )
        )
    return report


def _never_visible(scene: Any, sd: SceneData, ids: list[str]) -> str:
    """Why no pose of the built-in scene sees any of ``ids`` (the skip reason's detail)."""
    if all(scene.inside_closed_receptacle(scene.object_index[i]) for i in ids):
        return "inside a closed receptacle"
    known = [sd.instance_ids.index(i) for i in ids if i in sd.instance_ids]
    if np.isin(sd.view_instance, known).any():
        return "in view only farther than the success distance"
    return "in no pose's view (behind the simulator's walls or furniture)"


@dataclass
class _TargetMatch:
    """The built-in ids standing for an episode's target ids, how each matched, or why none could."""

    ids: list[str] = field(default_factory=list)
    problem: str | None = None
    exact: int = 0
    nearest: int = 0
    moved: int = 0
    dropped: int = 0


def _map_targets(scene: Any, ids: tuple[str, ...], max_distance: float) -> _TargetMatch:
    if not ids:
        return _TargetMatch(problem="no target: task_data is empty")
    match = _TargetMatch()
    unmatched: list[str] = []
    for object_id in ids:
        if object_id in scene.object_index:
            match.exact += 1
            match.ids.append(object_id)
            continue
        try:
            object_type, (x, _, z) = _id_type_and_position(object_id)
        except ValueError:
            return _TargetMatch(problem=f"target id without a position: {object_id!r}")
        candidates = [
            o for t in _v5_types(object_type) for o in (scene.objects[i] for i in scene.instances_of(t))
        ]
        if not candidates:
            unmatched.append(
                f"no object of that type in the scene: {object_type} ({object_id!r}, {scene.name})"
            )
            continue
        best = min(candidates, key=lambda o: math.hypot(o.center[0] - x, o.center[2] - z))
        distance = math.hypot(best.center[0] - x, best.center[2] - z)
        if distance <= max_distance:
            match.nearest += 1
            match.ids.append(best.id)
        elif len(candidates) == 1 and [object_type_of_id(i) for i in ids].count(object_type) == 1:
            # task_data lists every instance of the target type (SAVN's sampler does so, and in the
            # HOZ files each scene and type has one list throughout): one published instance and
            # one built-in instance are the same object, moved between AI2-THOR versions.
            match.moved += 1
            match.ids.append(best.id)
        else:
            unmatched.append(
                f"no object of that type nearby: nearest {best.id!r} is {distance:.2f} m from "
                f"{object_id!r} ({scene.name})"
            )
    if not match.ids:
        return _TargetMatch(problem=unmatched[0])
    # Success is seeing any listed instance: an instance the built-in scene lacks leaves the others.
    match.dropped = len(unmatched)
    match.ids = list(dict.fromkeys(match.ids))
    return match


def _start_pose(
    sd: SceneData,
    x: float,
    z: float,
    yaw: int,
    horizon: int,
    to_goal: np.ndarray,
    max_distance: float,
) -> tuple[tuple[float, float, int, int] | None, bool, int]:
    """The start, whether it moved, and its distance to the goal (-1: unreachable). Among the poses
    with the same yaw and horizon within ``max_distance`` (the published start itself first, where
    the built-in scene has it), the nearest that reaches the target off the pose graph's islands
    (``SceneData.usable_poses``), else the nearest that reaches it, else the nearest: the built-in
    grid lacks some positions of the published versions, and links between parts of a floor plan
    with them, while the published versions' graphs had no islands (one BFS made each)."""
    same = np.flatnonzero((sd.yaw == yaw) & (sd.horizon == horizon))
    d = np.hypot(sd.x[same] - x, sd.z[same] - z)
    within = d <= max_distance + 1e-6
    if not within.any():
        return None, False, -1
    near, d = same[within], d[within]
    reaches = to_goal[near] >= 0
    pose = int(near[np.lexsort((d, ~(reaches & sd.usable_poses[near]), ~reaches))[0]])
    start = (round(float(sd.x[pose]), 2), round(float(sd.z[pose]), 2), yaw, horizon)
    return start, pose_key(*start) != pose_key(x, z, yaw, horizon), int(to_goal[pose])


def _snap_to_grid(
    scene: Any, x: float, z: float, yaw: int, horizon: int, max_distance: float
) -> tuple[tuple[float, float, int, int] | None, bool]:
    grid = scene.reachable
    if not len(grid):
        return None, False
    d = np.hypot(grid[:, 0] - x, grid[:, 1] - z)
    best = int(np.argmin(d))
    if d[best] > max_distance:
        return None, False
    snapped = (round(float(grid[best, 0]), 2), round(float(grid[best, 1]), 2), yaw, horizon)
    return snapped, pose_key(*snapped) != pose_key(x, z, yaw, horizon)


def import_episode_file(path: str | Path, **kwargs: Any) -> MappingReport:
    """:func:`read_episode_file` then :func:`map_episodes`; malformed entries count as skipped."""
    episodes, bad = read_episode_file(path)
    report = map_episodes(episodes, **kwargs)
    report.skipped = sorted(bad + report.skipped)
    report.total += len(bad)
    return report
