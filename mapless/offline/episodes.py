"""Published evaluation episode pickles (SAVN, MJOLNIR, HOZ): read them and map them onto the
built-in scenes (writing ours in their format: :mod:`mapless.offline.episode_writer`).

Reading needs none of the original classes and never runs the file's code
(:mod:`mapless.offline.safe_pickle`): SAVN pickles hold a ``ThorAgentState`` start state and torch
GloVe tensors.

Mapping: AI2-THOR object ids changed between versions, so a target id is matched verbatim when
the built-in scene has it, else to the nearest object of the same type (v1 names translated) by
horizontal distance. Start poses snap to the nearest built-in pose with the same yaw and horizon.
Episodes that cannot be mapped are listed with the reason and skipped.
"""

from __future__ import annotations

import collections
import math
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
from mapless.offline.safe_pickle import Placeholder, load_untrusted
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
    except OSError as error:
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


@dataclass
class MappingReport:
    """Mapped episodes (``episode_id`` = ``import/<room>/<index in the file>``) and the skipped
    ones as ``(index in the file, reason)``."""

    episodes: list[Episode]
    skipped: list[tuple[int, str]]
    total: int
    exact_ids: int = 0
    nearest_ids: int = 0
    snapped_starts: int = 0

    @property
    def mapped(self) -> int:
        return len(self.episodes)

    def summary(self, max_reasons: int = 10) -> str:
        lines = [
            f"{self.mapped} of {self.total} episodes mapped, {len(self.skipped)} skipped",
            f"target ids: {self.exact_ids} matched verbatim, {self.nearest_ids} by type + nearest position",
            f"start poses: {self.snapped_starts} snapped to the nearest built-in pose",
        ]
        reasons = collections.Counter(_reason_kind(r) for _, r in self.skipped)
        for reason, count in reasons.most_common(max_reasons):
            example = next(f"#{i}: {r}" for i, r in self.skipped if _reason_kind(r) == reason)
            lines.append(f"  skipped {count}: {reason} (e.g. {example})")
        return "\n".join(lines)


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
) -> MappingReport:
    """Map published episodes onto the built-in scenes.

    ``scene_data(name)`` supplies the built-in SceneData, whose poses the starts snap to; without
    it starts snap to the scene's reachable grid (``load_scene(name).reachable``), yaw and horizon
    unchanged.
    """
    from mapless.scenes import load_scene
    from mapless.scenes.catalogue import canonical_scene

    report = MappingReport(episodes=[], skipped=[], total=0)
    for episode in episodes:
        report.total += 1
        try:
            name = canonical_scene(episode.scene)
        except MaplessError:
            report.skipped.append((episode.index, f"unknown scene: {episode.scene!r}"))
            continue
        scene = load_scene(name)
        mapped, problem, exact = _map_targets(scene, episode.target_ids, max_target_distance)
        if problem:
            report.skipped.append((episode.index, problem))
            continue
        x, z, yaw, horizon = episode.start
        if yaw % rotation_step:
            report.skipped.append((episode.index, f"start yaw not on the {rotation_step} degree grid: {yaw}"))
            continue
        start, snapped = _snap_start(name, scene, x, z, yaw % 360, horizon, scene_data, max_start_distance)
        if start is None:
            report.skipped.append(
                (episode.index, f"start pose not reachable: {pose_key(x, z, yaw, horizon)} in {name}")
            )
            continue
        target_types = [scene.object(i).type for i in mapped]
        goal = next((t for t in _v5_types(episode.target_type) if t in target_types), target_types[0])
        optimal = -1
        if scene_data is not None:
            sd = scene_data(name)
            known = [sd.instance_ids.index(i) for i in mapped if i in sd.instance_ids]
            distance = int(
                sd.distances_to(sd.goal_mask_for_instances(np.array(known, dtype=np.int64)))[
                    sd.pose_index[pose_key(*start)]
                ]
            )
            if distance < 0:
                report.skipped.append(
                    (
                        episode.index,
                        f"target not reachable from the start: {mapped} from {pose_key(*start)} in {name}",
                    )
                )
                continue
            optimal = distance + 1
        report.exact_ids += exact
        report.nearest_ids += len(episode.target_ids) - exact
        report.snapped_starts += snapped
        report.episodes.append(
            Episode(
                scene=name,
                target=goal,
                start=start,
                optimal_length=optimal,
                target_ids=tuple(mapped),
                episode_id=f"import/{scene.room_type}/{episode.index:04d}",
            )
        )
    return report


def _map_targets(scene: Any, ids: tuple[str, ...], max_distance: float) -> tuple[list[str], str | None, int]:
    if not ids:
        return [], "no target: task_data is empty", 0
    mapped: list[str] = []
    exact = 0
    for object_id in ids:
        if object_id in scene.object_index:
            exact += 1
            mapped.append(object_id)
            continue
        try:
            object_type, (x, _, z) = _id_type_and_position(object_id)
        except ValueError:
            return [], f"target id without a position: {object_id!r}", 0
        candidates = [
            o for t in _v5_types(object_type) for o in (scene.objects[i] for i in scene.instances_of(t))
        ]
        if not candidates:
            return [], f"no object of that type in the scene: {object_type} ({object_id!r}, {scene.name})", 0
        best = min(candidates, key=lambda o: math.hypot(o.center[0] - x, o.center[2] - z))
        distance = math.hypot(best.center[0] - x, best.center[2] - z)
        if distance > max_distance:
            return (
                [],
                (
                    f"no object of that type nearby: nearest {best.id!r} is {distance:.2f} m from "
                    f"{object_id!r} ({scene.name})"
                ),
                0,
            )
        mapped.append(best.id)
    return list(dict.fromkeys(mapped)), None, exact


def _snap_start(
    name: str,
    scene: Any,
    x: float,
    z: float,
    yaw: int,
    horizon: int,
    scene_data: Callable[[str], SceneData] | None,
    max_distance: float,
) -> tuple[tuple[float, float, int, int] | None, bool]:
    key = pose_key(x, z, yaw, horizon)
    if scene_data is not None:
        sd = scene_data(name)
        if key in sd.pose_index:
            return (x, z, yaw, horizon), False
        same = np.flatnonzero((sd.yaw == yaw) & (sd.horizon == horizon))
        if not len(same):
            return None, False
        d = np.hypot(sd.x[same] - x, sd.z[same] - z)
        best = int(same[np.argmin(d)])
        if d.min() > max_distance:
            return None, False
        return (round(float(sd.x[best]), 2), round(float(sd.z[best]), 2), yaw, horizon), True
    grid = scene.reachable
    if not len(grid):
        return None, False
    d = np.hypot(grid[:, 0] - x, grid[:, 1] - z)
    best = int(np.argmin(d))
    if d[best] > max_distance:
        return None, False
    snapped = (round(float(grid[best, 0]), 2), round(float(grid[best, 1]), 2), yaw, horizon)
    return snapped, pose_key(*snapped) != key


def import_episode_file(path: str | Path, **kwargs: Any) -> MappingReport:
    """:func:`read_episode_file` then :func:`map_episodes`; malformed entries count as skipped."""
    episodes, bad = read_episode_file(path)
    report = map_episodes(episodes, **kwargs)
    report.skipped = sorted(bad + report.skipped)
    report.total += len(bad)
    return report
