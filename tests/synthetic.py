"""Hand-built scenes with known geometry for simulator tests."""

from __future__ import annotations

import numpy as np

from mapless.scenes.floor_plans import Scene, SceneObject


def box(
    object_id: str,
    object_type: str,
    center,
    size,
    *,
    parents=(),
    receptacle=False,
    pickupable=False,
    openable=False,
    is_open=False,
    footprint=None,
) -> SceneObject:
    return SceneObject(
        id=object_id,
        type=object_type,
        center=tuple(float(c) for c in center),
        size=tuple(float(s) for s in size),
        footprint=footprint,
        parents=tuple(parents),
        receptacle=receptacle,
        pickupable=pickupable,
        moveable=False,
        openable=openable,
        is_open=is_open,
    )


def square_room(objects: list[SceneObject], half_width: float = 2.0, room_type: str = "kitchen") -> Scene:
    """A square room centred at the origin whose reachable grid covers |x|, |z| <= half_width - 0.5."""
    g = np.arange(-(half_width - 0.5), half_width - 0.5 + 1e-9, 0.25)
    xs, zs = np.meshgrid(g, g, indexing="ij")
    return Scene(
        name="Synthetic",
        room_type=room_type,
        split="train",
        floor_center=(0.0, -0.05, 0.0),
        floor_size=(2 * half_width, 0.1, 2 * half_width),
        reachable=np.stack([xs.ravel(), zs.ravel()], axis=1),
        objects=tuple(objects),
    )
