"""Scene variants: a floor plan under another arrangement of its small objects.

Name syntax: ``FloorPlanN@SOURCE:INDEX[:start]``.

* ``SOURCE`` ``rearrange2023`` (built-in: the 2023 Rearrangement dataset's training split, floor plans
  x01-x20, ``INDEX`` 0-49) or a path to a file in that dataset's format (its val and test splits, or
  one's own): ``INDEX`` is the episode of that floor plan, its goal arrangement (``target_poses``), or
  with ``:start`` its shuffled one (``starting_poses``);
* ``SOURCE`` ``gen``: the procedural generator (mapless.scenes.generator) with seed ``INDEX``, for any
  floor plan, the test ones included.

An arrangement is applied as the rearrangement environment applies it (``SetObjectPoses``): a
pickupable object it does not list is removed, a listed one moves to its pose, furniture stays (so the
reachable grid and the pose graph are the floor plan's), and listed openable objects take its
openness. A moved object's parent receptacle is the one it now rests on or in, so an object put
into a closed fridge is hidden as the default layout's are. Only the yaw of a rotation turns an
object's box: tilts about x and z (upright within 10 degrees for 94 % of the dataset's poses) are not
modelled.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib

import numpy as np

from mapless.errors import MaplessError
from mapless.scenes.arrangements import (
    Arrangement,
    ObjectPose,
    arrangement_of,
    episode_count,
    read_rearrangement,
)
from mapless.scenes.catalogue import GENERATED, VariantName, floor_plan_of, parse_variant
from mapless.scenes.floor_plans import (
    Scene,
    SceneObject,
    default_poses,
    default_poses_digest,
    load_floor_plan,
    turn_xz,
)
from mapless.scenes.generator import generate

#: Bump when applying an arrangement changes for the same arrangement (part of the cache key).
VARIANT_VERSION = 1
#: How far (m) a listed object's box may stand off the surface it rests on: the dataset's poses are
#: physics-settled, the boxes rounded to 1 mm.
SURFACE_TOLERANCE = 0.05
#: A box bottom this close to y = 0 rests on the floor.
FLOOR_HEIGHT = 0.05
#: Share of an arrangement's objects the floor plan must know before a missing one is a plain error
#: rather than an arrangement of another AI2-THOR version (other versions renamed every object).
SAME_VERSION_SHARE = 0.5


def arrangement_for(name: str | VariantName) -> Arrangement:
    """The arrangement a variant name stands for."""
    spec = parse_variant(name) if isinstance(name, str) else name
    if spec.source == GENERATED:
        return generate(spec.floor_plan, spec.index)
    return arrangement_of(spec.source, spec.floor_plan, spec.index, spec.phase)


def cache_stem(name: str) -> str:
    """The scene cache's file stem: the floor plan, or for a variant ``FloorPlanN@<hash>`` over the
    arrangement's content and how it is applied (two names of one arrangement share a file)."""
    if "@" not in name:
        return floor_plan_of(name)
    arrangement = arrangement_for(name)
    key = f"{arrangement.digest()}|{default_poses_digest()}|{VARIANT_VERSION}"
    return f"{arrangement.floor_plan}@{hashlib.sha256(key.encode()).hexdigest()[:16]}"


@functools.cache
def load_variant(name: str) -> Scene:
    spec = parse_variant(name)
    return apply_arrangement(load_floor_plan(spec.floor_plan), arrangement_for(spec), str(spec))


def moved_object(
    obj: SceneObject, default: tuple, pose: tuple[float, float, float], yaw: float
) -> SceneObject:
    """``obj`` with its pivot moved from ``default`` (x, y, z, yaw) to ``pose`` turned to ``yaw``: the
    box centre keeps its offset from the pivot, turned by the change of yaw."""
    pivot0, pivot = np.asarray(default[:3]), np.asarray(pose, dtype=float)
    turn = yaw - default[3]
    offset = np.asarray(obj.center) - pivot0
    offset[[0, 2]] = turn_xz(offset[None, [0, 2]], turn)[0]
    center = pivot + offset
    size = np.asarray(obj.size, dtype=float)
    footprint = None
    if obj.footprint is not None:
        corners = turn_xz(np.asarray(obj.footprint) - pivot0[[0, 2]], turn) + pivot[[0, 2]]
        footprint = tuple(tuple(round(float(v), 4) for v in p) for p in corners)
        size[[0, 2]] = corners.max(axis=0) - corners.min(axis=0)
    return dataclasses.replace(
        obj,
        center=tuple(round(float(v), 4) for v in center),
        size=tuple(round(float(v), 4) for v in size),
        footprint=footprint,
    )


def support_of(
    obj: SceneObject, others: list[SceneObject], pivot: tuple[float, float, float] | None = None
) -> tuple[str, ...] | None:
    """Where ``obj`` rests: ``(id,)`` of the smallest receptacle whose box holds its bottom centre
    (or its ``pivot``: a tilted object's box, turned by yaw only, can sink below its surface), else of
    the smallest piece of furniture (a shelving unit's shelves are boxes thinner than the unit),
    ``()`` for the floor, None when it floats off every surface."""
    bottom = obj.center[1] - obj.size[1] / 2
    points = np.array(
        [[obj.center[0], bottom, obj.center[2]], pivot or [obj.center[0], bottom, obj.center[2]]]
    )
    candidates = []
    for other in others:
        if other.id == obj.id or not (other.receptacle or not other.pickupable):
            continue
        inside = (other.box_min - SURFACE_TOLERANCE <= points) & (points <= other.box_max + SURFACE_TOLERANCE)
        if inside.all(axis=1).any():
            candidates.append((not other.receptacle, float(np.prod(other.size)), other.id))
    if candidates:
        return (min(candidates)[2],)
    return () if min(abs(bottom), abs(points[1, 1])) <= FLOOR_HEIGHT else None


#: A listed pose this close to the default one (m, degrees of yaw) leaves the object where it was.
UNMOVED = (0.01, 1.0)


def _at_default(pose: ObjectPose, default: tuple) -> bool:
    turn = abs((pose.rotation[1] - default[3] + 180) % 360 - 180)
    return bool(np.linalg.norm(np.subtract(pose.position, default[:3])) <= UNMOVED[0] and turn <= UNMOVED[1])


def apply_arrangement(scene: Scene, arrangement: Arrangement, name: str) -> Scene:
    """``scene`` under ``arrangement`` (module docstring), named ``name``. An object the floor plan
    lacks, or one left floating off every surface, is an error naming it; an arrangement most of whose
    objects the floor plan lacks is refused as one of another AI2-THOR version."""
    by_name = {o.name: o for o in scene.objects}
    listed = {p.name: p for p in arrangement.poses}
    unknown = [n for n in listed if n not in by_name]
    if unknown and len(unknown) > (1 - SAME_VERSION_SHARE) * len(listed):
        raise MaplessError(
            f"{name}: {len(unknown)} of the arrangement's {len(listed)} objects (e.g. {unknown[0]}) are not "
            f"in {scene.name}'s AI2-THOR 5.0 layout; the arrangement was made for another AI2-THOR version "
            "(object names change between versions; the 2023 Rearrangement dataset matches this one)"
        )
    if unknown:
        raise MaplessError(f"{name}: the arrangement places {unknown[0]}, which {scene.name} does not have")
    defaults = default_poses(scene.name)
    openness = dict(arrangement.openness)
    objects, moved = [], {}
    for obj in scene.objects:
        if obj.pickupable and obj.name not in listed:
            continue  # SetObjectPoses removes the pickupable objects it is not given
        if obj.pickupable:
            pose, default = listed[obj.name], defaults[obj.name]
            # An object left at its default pose keeps its default receptacle (and passes unchecked:
            # a bat leaning on a wall rests on no box).
            if not _at_default(pose, default):
                obj = moved_object(obj, default, pose.position, pose.rotation[1])
                moved[len(objects)] = pose.position
        if obj.openable and obj.name in openness:
            obj = dataclasses.replace(obj, is_open=openness[obj.name] > 0)
        objects.append(obj)
    for i, pivot in moved.items():
        parents = support_of(objects[i], objects, pivot)
        if parents is None:
            o = objects[i]
            raise MaplessError(
                f"{name}: the arrangement places {o.name} ({o.type}) at {o.center}, off any surface of "
                f"{scene.name} (no receptacle's or furniture's box holds it and it is not on the floor)"
            )
        objects[i] = dataclasses.replace(objects[i], parents=parents)
    return dataclasses.replace(scene, name=name, objects=tuple(objects))


def variants_of(floor_plan: str, source: str, count: int) -> list[str]:
    """The first ``count`` usable variants of ``floor_plan`` from ``source``: generator seeds 0, 1, ...,
    or the source's episodes in order, skipping those that cannot be applied (a few of the dataset's
    arrangements drop an object through the floor); fewer when the source runs out."""
    names: list[str] = []
    if source == GENERATED:
        return [f"{floor_plan_of(floor_plan)}@{GENERATED}:{i}" for i in range(count)]
    for index in range(episode_count(source, floor_plan_of(floor_plan))):
        if len(names) == count:
            break
        name = f"{floor_plan_of(floor_plan)}@{source}:{index}"
        try:
            load_variant(name)
        except MaplessError:
            continue
        names.append(name)
    return names


def source_facts(source: str, phase: str = "target") -> dict:
    """Measured facts about an arrangement source's ``phase`` arrangements against the default layouts:
    how many there are and apply, the share of listed objects whose pivot sits more than 0.5 m from its
    default, the share of pickupable objects each leaves out (removed), and the share of (floor plan,
    pickupable type) pairs that no arrangement of that floor plan lists."""
    data = read_rearrangement(source)
    counts = {"arrangements": 0, "applicable": 0, "listed": 0, "moved_05": 0, "slots": 0, "removed": 0}
    type_pairs, absent_pairs = 0, 0
    for floor_plan in sorted(data):
        scene, defaults = load_floor_plan(floor_plan), default_poses(floor_plan)
        pickupable = [o for o in scene.objects if o.pickupable]
        listed_types: set[str] = set()
        for index in range(len(data[floor_plan])):
            arrangement = arrangement_of(source, floor_plan, index, phase)
            names = {p.name for p in arrangement.poses}
            counts["arrangements"] += 1
            counts["slots"] += len(pickupable)
            counts["removed"] += sum(o.name not in names for o in pickupable)
            listed_types |= {o.type for o in pickupable if o.name in names}
            for pose in arrangement.poses:
                if pose.name in defaults:
                    counts["listed"] += 1
                    counts["moved_05"] += (
                        np.linalg.norm(np.subtract(pose.position, defaults[pose.name][:3])) > 0.5
                    )
            try:
                apply_arrangement(scene, arrangement, f"{floor_plan}@{source}:{index}")
                counts["applicable"] += 1
            except MaplessError:
                pass
        types = {o.type for o in pickupable}
        type_pairs += len(types)
        absent_pairs += len(types - listed_types)
    return {
        "floor_plans": len(data),
        **counts,
        "moved_share": counts["moved_05"] / max(counts["listed"], 1),
        "removed_share": counts["removed"] / max(counts["slots"], 1),
        "absent_type_share": absent_pairs / max(type_pairs, 1),
    }
