"""Static scene knowledge: the 120 iTHOR floor plans, splits, category sets, targets."""

from mapless.scenes.catalogue import ROOM_TYPES, SPLITS, room_type_of, scene_names, split_of
from mapless.scenes.floor_plans import Scene, SceneObject
from mapless.scenes.layout import load_scene

__all__ = [
    "ROOM_TYPES",
    "SPLITS",
    "Scene",
    "SceneObject",
    "load_scene",
    "room_type_of",
    "scene_names",
    "split_of",
]
