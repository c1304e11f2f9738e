"""Arrangements in the AI2-THOR Rearrangement dataset's format (the 2023 dataset's ``{train, val,
test}.pkl.gz``): where a floor plan's movable objects sit.

A file is a (gzip-compressed) pickle of ``{"FloorPlan{N}": [episode, ...]}``; each episode holds two
arrangements of the floor plan, ``target_poses`` (the goal the rearrangement walkthrough shows) and
``starting_poses`` (the shuffled one), each a list of ``{name, objectName, position {x, y, z},
rotation {x, y, z}}``, plus ``openable_data`` with each listed openable object's ``start_openness``
and ``target_openness``. The pickles hold only plain Python values, so they are read with an
unpickler that refuses every global: a crafted file cannot run code.

The built-in source ``rearrange2023`` is that dataset's training split (80 floor plans x01-x20, 50
episodes each), shipped byte for byte in ``mapless/data/variants/`` (mapless/data/NOTICE.md).
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import io
import json
import math
import pickle
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from mapless.errors import MaplessError
from mapless.safe_pickle import check_opcodes
from mapless.scenes.catalogue import PHASES

BUILTIN_SOURCES = {"rearrange2023": "variants/rearrange2023_train.pkl.gz"}
#: Each phase's (PHASES) keys of the poses and of the openness in a dataset episode.
PHASE_KEYS = dict(
    zip(PHASES, (("target_poses", "target_openness"), ("starting_poses", "start_openness")), strict=True)
)


@dataclass(frozen=True)
class ObjectPose:
    """An object's pivot ``position`` (m) and ``rotation`` (degrees about x, y, z), as AI2-THOR's
    ``SetObjectPoses`` takes them; ``name`` is the object's AI2-THOR name (``Apple_3fef4551``)."""

    name: str
    position: tuple[float, float, float]
    rotation: tuple[float, float, float]


@dataclass(frozen=True)
class Arrangement:
    """One arrangement of a floor plan: the poses of the objects it lists (pickupable objects it does
    not list are removed) and the openness (0-1) of the openable objects it lists."""

    floor_plan: str
    poses: tuple[ObjectPose, ...]
    openness: tuple[tuple[str, float], ...] = ()

    def digest(self) -> str:
        """Hash of the content (not of where it came from): the scene cache's key of the variant."""
        payload = {
            "floor_plan": self.floor_plan,
            "poses": [[p.name, *p.position, *p.rotation] for p in self.poses],
            "openness": [list(o) for o in self.openness],
        }
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


class _PlainValues(pickle.Unpickler):
    """Unpickles dicts, lists, strings and numbers only: any class or function is refused."""

    def find_class(self, module: str, name: str):
        raise pickle.UnpicklingError(
            f"refusing to load {module}.{name}: an arrangement file holds plain values"
        )


def source_path(source: str) -> Path:
    """The file of an arrangement source: a built-in name or a path to a file in the format."""
    if source in BUILTIN_SOURCES:
        return Path(str(resources.files("mapless.data").joinpath(BUILTIN_SOURCES[source])))
    return Path(source)


def read_rearrangement(source: str) -> dict[str, list[dict]]:
    """``{floor plan: [episode, ...]}`` of a source (built-in name or file path), checked for shape."""
    path = source_path(source)
    try:
        stat = path.stat()
    except OSError as error:
        raise MaplessError(
            f"cannot read arrangement file {path}: {error.strerror or error} (arrangement sources: "
            f"{', '.join(BUILTIN_SOURCES)}, or a file in the rearrangement dataset's format)"
        ) from None
    return _read(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@functools.cache
def _read(path: str, _mtime: int, _size: int) -> dict[str, list[dict]]:
    """Cached per file version (the stat fields are part of the key, so an edited file is re-read)."""
    raw = Path(path).read_bytes()
    try:
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        check_opcodes(raw)  # a few bytes may claim gigabytes (the episode reader's guard)
        data = _PlainValues(io.BytesIO(raw)).load()
    except (
        pickle.UnpicklingError,
        EOFError,
        zlib.error,
        ValueError,
        TypeError,
        IndexError,
        OSError,
    ) as error:
        raise MaplessError(
            f"{path}: not an arrangement file in the rearrangement dataset's format ({error})"
        ) from None
    if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
        raise MaplessError(f"{path}: expected a mapping of floor plan names to lists of episodes")
    return data


def episode_count(source: str, floor_plan: str) -> int:
    return len(read_rearrangement(source).get(floor_plan, []))


def arrangement_of(source: str, floor_plan: str, index: int, phase: str = "target") -> Arrangement:
    """Arrangement ``phase`` (``target`` or ``start``) of episode ``index`` of ``floor_plan``."""
    episodes = read_rearrangement(source).get(floor_plan, [])
    if not 0 <= index < len(episodes):
        held = f"episodes 0-{len(episodes) - 1}" if episodes else "no episode"
        raise MaplessError(f"arrangement source {source!r} holds {held} of {floor_plan}, not {index}")
    if phase not in PHASES:
        raise MaplessError(f"unknown arrangement phase {phase!r}; valid: {', '.join(PHASES)}")
    episode = episodes[index]
    where = f"{source}, {floor_plan} episode {index}"
    pose_key, open_key = PHASE_KEYS[phase]
    if not isinstance(episode, dict) or not isinstance(episode.get(pose_key), list):
        raise MaplessError(f"{where}: no {pose_key!r} list (not the rearrangement dataset's format)")
    try:
        poses = tuple(
            ObjectPose(
                str(p["name"]),
                tuple(float(p["position"][k]) for k in "xyz"),
                tuple(float(p["rotation"][k]) for k in "xyz"),
            )
            for p in episode[pose_key]
        )
        openness = tuple(
            sorted((str(o["name"]), float(o[open_key])) for o in episode.get("openable_data") or [])
        )
    except (KeyError, TypeError, ValueError, OverflowError) as error:  # float(10**400) overflows
        raise MaplessError(
            f"{where}: malformed pose or openness entry ({type(error).__name__}: {error})"
        ) from None
    numbers = [v for p in poses for v in (*p.position, *p.rotation)] + [v for _, v in openness]
    if not all(math.isfinite(v) for v in numbers):  # a NaN pose would place an object nowhere
        raise MaplessError(f"{where}: a pose or openness that is not a finite number")
    return Arrangement(floor_plan, poses, openness)
