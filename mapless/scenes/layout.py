"""Any scene's layout by name: a built-in floor plan's (mapless.scenes.floor_plans) or a scene
variant's, the floor plan under another arrangement (mapless.scenes.variants)."""

from __future__ import annotations

from mapless.scenes.catalogue import canonical_scene
from mapless.scenes.floor_plans import Scene, load_floor_plan
from mapless.scenes.variants import load_variant


def load_scene(name: str) -> Scene:
    """The layout of ``FloorPlanN`` (``_physics`` suffix accepted) or of a scene variant
    ``FloorPlanN@SOURCE:INDEX`` (both loaded once: their loaders cache)."""
    name = canonical_scene(name)
    return load_variant(name) if "@" in name else load_floor_plan(name)
