"""Procedural arrangements: every pickupable object of a floor plan put on a plausible receptacle,
seeded, for floor plans without published arrangements (the val and test floor plans).

The rule, object by object in the layout's order, with ``numpy.random.default_rng([GENERATOR_VERSION,
floor plan number, seed])``:

1. a receptacle type, drawn with probability P(type | object type, room type): the share of that
   object type's instances resting on (or in) that receptacle type in the default layouts of the
   training floor plans x01-x20 only (so the val and test layouts inform nothing), restricted to the
   furniture receptacle types this floor plan has. An object type that training never places on one
   of them keeps its default receptacle's type (or the floor);
2. one of the floor plan's receptacles of that type, uniformly;
3. a yaw: the default one turned by 0, 90, 180 or 270 degrees, uniformly;
4. a point: uniform over the receptacle's box shrunk by the object's half extent, on its top, or on
   its bottom for receptacles that close (Fridge, Cabinet, Drawer, ...: the object is inside); up
   to ``TRIES`` draws keep it off the footprints of objects already put on the same receptacle.

Every object stays in the floor plan (the rearrangement dataset also removes some; this generator
only moves). The result is an :class:`~mapless.scenes.arrangements.Arrangement` of pivots, applied
as any other (mapless.scenes.variants), and bit-for-bit the same on every run.
"""

from __future__ import annotations

import functools
from collections import Counter, defaultdict

import numpy as np

from mapless.scenes.arrangements import Arrangement, ObjectPose
from mapless.scenes.catalogue import _number, floor_plan_of, scene_names
from mapless.scenes.floor_plans import (
    CLOSING_RECEPTACLES,
    Scene,
    SceneObject,
    default_poses,
    load_floor_plan,
    turn_xz,
)

#: Bump when the rule changes: it seeds the generator, so every generated arrangement changes with it.
GENERATOR_VERSION = 1
TRIES = 20
#: Gap (m) kept between a placed object's footprint and its receptacle's box edge.
EDGE = 0.02


def furniture_support(scene: Scene, obj: SceneObject) -> SceneObject | None:
    """The first non-pickupable receptacle below ``obj`` (a mug on a plate on a table: the table)."""
    parents = list(obj.parents)
    while parents:
        parent_id = parents.pop(0)
        if parent_id not in scene.object_index:
            continue
        parent = scene.object(parent_id)
        if not parent.pickupable:
            return parent
        parents = list(parent.parents)
    return None


@functools.cache
def receptacle_prior(room_type: str) -> dict[str, dict[str, float]]:
    """P(receptacle type | object type) of a room type, counted in the training floor plans' layouts."""
    counts: dict[str, Counter] = defaultdict(Counter)
    for name in scene_names("train", (room_type,)):
        scene = load_floor_plan(name)
        for obj in scene.objects:
            support = furniture_support(scene, obj) if obj.pickupable else None
            if support is not None:
                counts[obj.type][support.type] += 1
    return {
        kind: {t: n / sum(c.values()) for t, n in sorted(c.items())} for kind, c in sorted(counts.items())
    }


def _offset_and_extent(obj: SceneObject, turn: float) -> tuple[np.ndarray, np.ndarray]:
    """The footprint's corners relative to the box centre after turning by ``turn`` degrees, and the
    half extents (x, z) of their axis-aligned box."""
    centre = np.asarray(obj.center, dtype=float)[[0, 2]]
    if obj.footprint is not None:
        corners = np.asarray(obj.footprint, dtype=float) - centre
    else:
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * np.asarray(obj.size)[[0, 2]] / 2
    relative = turn_xz(corners, turn)
    return relative, np.abs(relative).max(axis=0)


def _overlaps(corners: np.ndarray, placed: list[np.ndarray]) -> bool:
    """Axis-aligned overlap of xz corner sets (a conservative test for the small objects moved)."""
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return any(np.all(lo < p.max(axis=0)) and np.all(p.min(axis=0) < hi) for p in placed)


def generate(floor_plan: str, seed: int) -> Arrangement:
    """The generated arrangement ``seed`` of ``floor_plan`` (module docstring)."""
    floor_plan = floor_plan_of(floor_plan)
    scene = load_floor_plan(floor_plan)
    prior = receptacle_prior(scene.room_type)
    defaults = default_poses(floor_plan)
    rng = np.random.default_rng([GENERATOR_VERSION, _number(floor_plan), seed])
    receptacles: dict[str, list[SceneObject]] = defaultdict(list)
    for obj in scene.objects:
        if obj.receptacle and not obj.pickupable:
            receptacles[obj.type].append(obj)
    placed: dict[str, list[np.ndarray]] = defaultdict(list)
    poses = []
    for obj in scene.objects:
        if not obj.pickupable:
            continue
        weights = {t: p for t, p in prior.get(obj.type, {}).items() if t in receptacles}
        if not weights:
            default = furniture_support(scene, obj)
            weights = {default.type: 1.0} if default is not None and default.type in receptacles else {}
        if weights:
            types = sorted(weights)
            p = np.array([weights[t] for t in types])
            kind = types[rng.choice(len(types), p=p / p.sum())]
            support = receptacles[kind][rng.integers(len(receptacles[kind]))]
        else:
            support = None  # on the floor where it is: a type no receptacle of this floor plan holds
        turn = float(90 * rng.integers(4)) if support is not None else 0.0  # unsupported: left as it is
        relative, half = _offset_and_extent(obj, turn)
        if support is None:
            center = np.asarray(obj.center, dtype=float)
        else:
            lo, hi = support.box_min, support.box_max
            inside = support.type in CLOSING_RECEPTACLES
            bottom = lo[1] + EDGE if inside else hi[1]
            # The box shrunk by the object's half extent; a receptacle smaller than the object: its centre.
            middle = (lo[[0, 2]] + hi[[0, 2]]) / 2
            low = np.minimum(lo[[0, 2]] + half + EDGE, middle)
            high = np.maximum(hi[[0, 2]] - half - EDGE, middle)
            for _ in range(TRIES):
                xz = rng.uniform(low, high)
                if not _overlaps(relative + xz, placed[support.id]):
                    break
            placed[support.id].append(relative + xz)
            center = np.array([xz[0], bottom + obj.size[1] / 2, xz[1]])
        default = defaults[obj.name]
        pivot_offset = np.asarray(obj.center) - np.asarray(default[:3])
        pivot_offset[[0, 2]] = turn_xz(pivot_offset[None, [0, 2]], turn)[0]
        pivot = center - pivot_offset
        poses.append(
            ObjectPose(
                obj.name,
                tuple(round(float(v), 4) for v in pivot),
                (0.0, round(float((default[3] + turn) % 360), 4), 0.0),
            )
        )
    return Arrangement(floor_plan, tuple(poses))
