"""Names, room types and splits of the 120 iTHOR floor plans.

Room type r in {kitchen, living_room, bedroom, bathroom} owns FloorPlan{100*i + n}, n = 1..30
(kitchens have no hundreds digit). Splits (allenact/rearrangement convention):
``train`` = n 1-20, ``val`` = n 21-25, ``test`` = n 26-30. The ``paper`` protocol evaluates on
n 21-30, as the paper (and MJOLNIR) did; it is labelled as such wherever it is reported. The
``reference`` protocol uses the split of SAVN's published episode pickles: ``ref_val`` = the odd
n 21-29, ``ref_test`` = the even n 22-30 (mapless.episodes.protocols).

A scene variant, a floor plan under another arrangement of its small objects
(mapless.scenes.variants), is named ``FloorPlanN@SOURCE:INDEX[:start]``; the syntax is here, with
the floor plans' names, so that every module naming scenes reads it without loading arrangements.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapless.errors import MaplessError, UnknownNameError

ROOM_TYPES: tuple[str, ...] = ("kitchen", "living_room", "bedroom", "bathroom")
SPLITS: dict[str, range] = {
    "train": range(1, 21),
    "val": range(21, 26),
    "test": range(26, 31),
    "paper": range(21, 31),
    "ref_val": range(21, 30, 2),
    "ref_test": range(22, 31, 2),
    "all": range(1, 31),
}
_ROOM_OFFSET = {"kitchen": 0, "living_room": 200, "bedroom": 300, "bathroom": 400}
#: A variant's source of procedurally generated arrangements (mapless.scenes.generator).
GENERATED = "gen"
#: Which arrangement of a dataset episode a variant takes: its goal (``target``, the default) or the
#: shuffled one it starts from (``start``); mapless.scenes.arrangements reads each from the file.
PHASES = ("target", "start")
SYNTAX = "FloorPlanN@SOURCE:INDEX[:start] (SOURCE: rearrange2023, gen, or an arrangement file)"
_SCENE_SUMMARY = "FloorPlan1-30 (kitchens), FloorPlan201-230 (living rooms), FloorPlan301-330 (bedrooms), FloorPlan401-430 (bathrooms)"


def _unknown_scene(scene: str) -> UnknownNameError:
    return UnknownNameError("scene", scene, scene_names("all"), summary=_SCENE_SUMMARY)


def scene_name(room_type: str, index: int) -> str:
    return f"FloorPlan{_ROOM_OFFSET[room_type] + index}"


def _number(scene: str) -> int:
    if not scene.startswith("FloorPlan"):
        raise _unknown_scene(scene)
    digits = scene.partition("@")[0][len("FloorPlan") :].removesuffix("_physics")
    if not digits.isdigit():
        raise _unknown_scene(scene)
    number = int(digits)
    hundreds, index = divmod(number, 100)
    if index < 1 or index > 30 or hundreds not in (0, 2, 3, 4):
        raise _unknown_scene(scene)
    return number


def canonical_scene(scene: str) -> str:
    """``FloorPlan28_physics`` -> ``FloorPlan28``; raises on names outside the 120 floor plans. A
    scene variant's name (``FloorPlan28@gen:3``, mapless.scenes.variants) keeps its arrangement, in
    canonical form, after checking its syntax."""
    if "@" in scene:
        return str(parse_variant(scene))
    return f"FloorPlan{_number(scene)}"


@dataclass(frozen=True)
class VariantName:
    floor_plan: str
    source: str
    index: int
    phase: str = "target"

    def __str__(self) -> str:
        suffix = "" if self.phase == "target" else f":{self.phase}"
        return f"{self.floor_plan}@{self.source}:{self.index}{suffix}"


def parse_variant(name: str) -> VariantName:
    """The parts of a variant name; a malformed one is an error quoting the syntax."""
    base, _, rest = name.partition("@")
    head, _, last = rest.rpartition(":")
    phase = "target"
    if last in PHASES and ":" in head:
        phase = last
        head, _, last = head.rpartition(":")
    if not head or not last.isdigit():
        raise MaplessError(f"scene variant {name!r}: expected {SYNTAX}")
    if head == GENERATED and phase != "target":
        raise MaplessError(f"scene variant {name!r}: a generated arrangement has no {phase!r} phase")
    _number(base)  # raises on a name outside the 120 floor plans
    return VariantName(floor_plan_of(base), head, int(last), phase)


def floor_plan_of(scene: str) -> str:
    """The floor plan of a scene or scene variant: ``FloorPlan28@gen:3`` -> ``FloorPlan28``."""
    return f"FloorPlan{_number(scene)}"


def room_type_of(scene: str) -> str:
    return {0: "kitchen", 2: "living_room", 3: "bedroom", 4: "bathroom"}[_number(scene) // 100]


def split_of(scene: str) -> str:
    index = _number(scene) % 100
    return next(s for s in ("train", "val", "test") if index in SPLITS[s])


def split_range_label(split: str) -> str:
    """``x21-x25``; ``x21-x29 odd`` for the reference protocol's every-other-plan splits."""
    numbers = SPLITS[split]
    label = f"x{numbers[0]:02d}-x{numbers[-1]:02d}"
    if numbers.step == 2:
        label += " odd" if numbers[0] % 2 else " even"
    return label


def scene_names(split: str = "all", room_types: tuple[str, ...] | list[str] = ROOM_TYPES) -> list[str]:
    """Floor plans of a split, room type by room type in ``ROOM_TYPES`` order."""
    if split not in SPLITS:
        raise UnknownNameError("split", split, SPLITS)
    for room in room_types:
        if room not in ROOM_TYPES:
            raise UnknownNameError("room type", room, ROOM_TYPES)
    return [scene_name(room, i) for room in room_types for i in SPLITS[split]]


def resolve_scenes(spec: str | list[str]) -> list[str]:
    """Scene selection from a CLI/config spec: a split name, ``split:room``, or explicit names."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names: list[str] = []
    for item in (s.strip() for s in items):
        if not item:
            continue
        if item.startswith("FloorPlan"):
            names.append(canonical_scene(item))
        else:
            split, _, room = item.partition(":")
            names.extend(scene_names(split, (room,) if room else ROOM_TYPES))
    return names
