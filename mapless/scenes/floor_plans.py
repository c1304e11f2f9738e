"""The 120 built-in floor plans as shipped: each one's objects (boxes, receptacles), floor extent
and reachable grid, and its movable objects' default poses. Everything above it in ``scenes/``
(the generator, scene variants, :func:`mapless.scenes.layout.load_scene`) builds on these."""

from __future__ import annotations

import functools
import gzip
import hashlib
import json
from dataclasses import dataclass
from importlib import resources

import numpy as np

from mapless.scenes.catalogue import canonical_scene, room_type_of, split_of

SCENE_FILE = "scenes/ithor_v5_scenes.json.gz"
POSE_FILE = "scenes/ithor_v5_poses.json.gz"

#: Receptacles whose contents are hidden while closed (AI2-THOR default state is read per object).
CLOSING_RECEPTACLES = frozenset({"Fridge", "Cabinet", "Drawer", "Microwave", "Safe", "Box", "LaundryHamper"})


@dataclass(frozen=True)
class SceneObject:
    id: str
    type: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    footprint: tuple[tuple[float, float], ...] | None  # oriented xz corners, movable objects only
    parents: tuple[str, ...]
    receptacle: bool
    pickupable: bool
    moveable: bool
    openable: bool
    is_open: bool
    name: str = ""  # AI2-THOR's object name (``Apple_3fef4551``), what arrangements refer to

    @property
    def box_min(self) -> np.ndarray:
        return np.asarray(self.center) - np.asarray(self.size) / 2

    @property
    def box_max(self) -> np.ndarray:
        return np.asarray(self.center) + np.asarray(self.size) / 2

    @property
    def hides_contents(self) -> bool:
        return self.type in CLOSING_RECEPTACLES and not self.is_open


@dataclass(frozen=True)
class Scene:
    name: str
    room_type: str
    split: str
    floor_center: tuple[float, float, float]
    floor_size: tuple[float, float, float]
    reachable: np.ndarray  # (n, 2) x, z on the 0.25 m grid
    objects: tuple[SceneObject, ...]

    def object(self, object_id: str) -> SceneObject:
        return self.objects[self.object_index[object_id]]

    @functools.cached_property
    def object_index(self) -> dict[str, int]:
        return {o.id: i for i, o in enumerate(self.objects)}

    def instances_of(self, object_type: str) -> list[int]:
        return [i for i, o in enumerate(self.objects) if o.type == object_type]

    def inside_closed_receptacle(self, index: int) -> bool:
        """True when the object, or any receptacle holding it, sits in a closed container."""
        seen: set[str] = set()
        stack = list(self.objects[index].parents)
        while stack:
            parent_id = stack.pop()
            if parent_id in seen or parent_id not in self.object_index:
                continue
            seen.add(parent_id)
            parent = self.object(parent_id)
            if parent.hides_contents:
                return True
            stack.extend(parent.parents)
        return False


@functools.cache
def raw_scenes() -> dict:
    """The shipped floor plans' records by name, as stored (the category sets read their types)."""
    with resources.files("mapless.data").joinpath(SCENE_FILE).open("rb") as f:
        return json.loads(gzip.decompress(f.read()))["scenes"]


def _as_object(raw: dict) -> SceneObject:
    footprint = tuple(tuple(p) for p in raw["footprint"]) if raw["footprint"] else None
    return SceneObject(
        id=raw["id"],
        type=raw["type"],
        center=tuple(raw["center"]),
        size=tuple(raw["size"]),
        footprint=footprint,
        parents=tuple(raw["parents"]),
        receptacle=raw["receptacle"],
        pickupable=raw["pickupable"],
        moveable=raw["moveable"],
        openable=raw["openable"],
        is_open=raw["is_open"],
        name=raw.get("name", ""),
    )


@functools.cache
def load_floor_plan(name: str) -> Scene:
    """The built-in layout of ``FloorPlanN`` (``_physics`` suffix accepted). A scene variant's name
    is refused rather than read as its floor plan: :func:`mapless.scenes.layout.load_scene` loads
    any scene."""
    if "@" in name:
        raise ValueError(f"{name} is a scene variant, not a floor plan: load it with load_scene")
    name = canonical_scene(name)
    raw = raw_scenes()[name]
    return Scene(
        name=name,
        room_type=room_type_of(name),
        split=split_of(name),
        floor_center=tuple(raw["floor_center"]),
        floor_size=tuple(raw["floor_size"]),
        reachable=np.asarray(raw["reachable"], dtype=np.float64),
        objects=tuple(_as_object(o) for o in raw["objects"] if o["type"] != "Floor"),
    )


@functools.cache
def _pose_data() -> dict:
    raw = resources.files("mapless.data").joinpath(POSE_FILE).read_bytes()
    return {"digest": hashlib.sha256(raw).hexdigest(), "scenes": json.loads(gzip.decompress(raw))["scenes"]}


def default_poses(floor_plan: str) -> dict[str, tuple[float, float, float, float]]:
    """Default pivot ``(x, y, z, yaw)`` of the floor plan's movable objects, by AI2-THOR name."""
    return {k: tuple(v) for k, v in _pose_data()["scenes"][floor_plan].items()}


def default_poses_digest() -> str:
    """sha256 of the shipped default poses (a variant's cache key: they say where objects move from)."""
    return _pose_data()["digest"]


def turn_xz(points: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate ``[n, 2]`` xz offsets by a yaw in degrees, as AI2-THOR turns (clockwise seen from
    above: +z turns to +x)."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    return np.stack([points[:, 0] * c + points[:, 1] * s, -points[:, 0] * s + points[:, 1] * c], axis=1)
