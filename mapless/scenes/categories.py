"""Category sets (the nodes of context vectors and knowledge graphs) and navigation targets.

The default category set is MJOLNIR's 101 GCN nodes (``all_objects_v1.txt``, AI2-THOR 1.0.1 type
names). AI2-THOR 5 renamed or dropped some of them; :data:`V1_TO_V5` maps every v1 name onto the
v5 types whose instances count as that category (see docs/guide/simulator.md):

* ``TableTop``   -> ``DiningTable``, ``CoffeeTable`` (v2 split the generic table type)
* ``NightStand`` -> ``SideTable`` (renamed in v2)
* ``Glassbottle``-> ``Bottle`` (renamed in v2)
* ``Cart``, ``Lamp``, ``ToiletPaperRoll``: no v5 counterpart; their rows stay zero. (``Lamp``'s
  instances became ``FloorLamp``/``DeskLamp``, already categories; ``ToiletPaperRoll`` became
  ``ToiletPaper``, also already a category.)

``all_types`` instead uses every v5 type present in the 120 default scenes (117, ``Floor`` excluded).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources

from mapless.errors import UnknownNameError
from mapless.scenes.floor_plans import raw_scenes

V1_TO_V5: dict[str, tuple[str, ...]] = {
    "TableTop": ("DiningTable", "CoffeeTable"),
    "NightStand": ("SideTable",),
    "Glassbottle": ("Bottle",),
    "Cart": (),
    "Lamp": (),
    "ToiletPaperRoll": (),
}

#: MJOLNIR's 22 targets (datasets/constants.py), per room type.
MJOLNIR_TARGETS: dict[str, tuple[str, ...]] = {
    "kitchen": ("Toaster", "Spatula", "Bread", "Mug", "CoffeeMachine", "Apple"),
    "living_room": ("Painting", "Laptop", "Television", "RemoteControl", "Vase", "ArmChair"),
    "bedroom": ("Blinds", "DeskLamp", "Pillow", "AlarmClock", "CD"),
    "bathroom": ("Mirror", "ToiletPaper", "SoapBar", "Towel", "SprayBottle"),
}
#: SAVN's targets. ``CoffeeMaker`` is v5's ``CoffeeMachine``; SAVN's ``Lamp`` is v5's ``DeskLamp``
#: (bedroom table lamps; v5 has no ``Lamp`` type).
SAVN_TARGETS: dict[str, tuple[str, ...]] = {
    "kitchen": ("Toaster", "Microwave", "Fridge", "CoffeeMachine", "GarbageCan", "Box", "Bowl"),
    "living_room": ("Pillow", "Laptop", "Television", "GarbageCan", "Box", "Bowl"),
    "bedroom": ("HousePlant", "DeskLamp", "Book", "AlarmClock"),
    "bathroom": ("Sink", "ToiletPaper", "SoapBottle", "LightSwitch"),
}
#: The HOZ line's 22 classes (HOZ, VTNet, DOA, MT), per room type: the union of the goal types of
#: its published val and test episode files of that room type (mapless/data/episodes/hoz22/, the
#: reference protocol's published sets; kitchen ``CellPhone`` occurs in the test file only). Only 7
#: of the 22 are MJOLNIR targets. Every class is a category of ``mjolnir101`` and of ``all_types``
#: (a context row, a graph node and a GloVe vector in both; tests/test_target_sets.py) and occurs in
#: the training floor plans x01-x20 of its room type.
HOZ22_TARGETS: dict[str, tuple[str, ...]] = {
    "kitchen": (
        "Bowl", "CellPhone", "Chair", "CoffeeMachine", "Fridge", "GarbageCan", "Kettle", "LightSwitch",
        "Microwave", "Pan", "Plate", "Pot", "Sink", "StoveBurner", "Toaster",
    ),
    "living_room": (
        "Book", "CellPhone", "Chair", "DeskLamp", "FloorLamp", "GarbageCan", "Laptop", "LightSwitch",
        "RemoteControl", "Television",
    ),
    "bedroom": ("AlarmClock", "Book", "CellPhone", "Chair", "DeskLamp", "GarbageCan", "Laptop", "LightSwitch"),
    "bathroom": ("GarbageCan", "LightSwitch", "Sink"),
}  # fmt: skip
TARGET_SETS = {"mjolnir22": MJOLNIR_TARGETS, "savn": SAVN_TARGETS, "hoz22": HOZ22_TARGETS}
CATEGORY_SETS = ("mjolnir101", "all_types")


@dataclass(frozen=True)
class CategorySet:
    """Ordered category names plus the v5 object type -> category row mapping."""

    name: str
    names: tuple[str, ...]
    type_to_index: dict[str, int]

    def __len__(self) -> int:
        return len(self.names)

    def index(self, category: str) -> int:
        try:
            return self.names.index(category)
        except ValueError:
            raise UnknownNameError("category", category, self.names) from None


@functools.cache
def category_set(name: str = "mjolnir101") -> CategorySet:
    if name == "mjolnir101":
        text = resources.files("mapless.data").joinpath("scenes/mjolnir_all_objects_v1.txt").read_text()
        names = tuple(text.split())
        type_to_index = {}
        for i, category in enumerate(names):
            for v5_type in V1_TO_V5.get(category, (category,)):
                type_to_index[v5_type] = i
        return CategorySet(name, names, type_to_index)
    if name == "all_types":
        types = sorted({o["type"] for s in raw_scenes().values() for o in s["objects"]} - {"Floor"})
        return CategorySet(name, tuple(types), {t: i for i, t in enumerate(types)})
    raise UnknownNameError("category set", name, CATEGORY_SETS)


def targets(target_set: str = "mjolnir22") -> dict[str, tuple[str, ...]]:
    if target_set not in TARGET_SETS:
        raise UnknownNameError("target set", target_set, TARGET_SETS)
    return TARGET_SETS[target_set]


def all_targets(target_set: str = "mjolnir22") -> tuple[str, ...]:
    """Every target of the set once, in room order (SAVN repeats some across rooms)."""
    return tuple(dict.fromkeys(t for room in targets(target_set).values() for t in room))
