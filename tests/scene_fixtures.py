"""Small hand-made :class:`SceneData` objects for backend tests (no simulator needed)."""

from __future__ import annotations

import math

import numpy as np

from mapless.actions import N_MOVEMENT_ACTIONS
from mapless.offline.format import category_rows, context_from_boxes
from mapless.scenes.categories import category_set
from mapless.sim.scene_data import SceneData

#: id, type; two Mugs (box attribution within a type), a DiningTable/CoffeeTable pair (v1 alias
#: ``TableTop``), a Toaster, a never-visible Apple and a type outside the category set.
INSTANCES = (
    ("Mug|+00.40|+00.90|+00.60", "Mug"),
    ("Mug|-00.30|+00.90|+00.60", "Mug"),
    ("DiningTable|+00.10|+00.00|+00.90", "DiningTable"),
    ("CoffeeTable|-00.50|+00.00|-00.40", "CoffeeTable"),
    ("Toaster|+00.80|+00.90|-00.20", "Toaster"),
    ("Apple|+00.00|+00.80|+01.00", "Apple"),
    ("Stool|+00.70|+00.00|+00.70", "Stool"),
)


def grid_scene(
    positions: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.25, 0.0), (0.0, 0.25), (0.25, 0.25)),
    horizons: tuple[int, ...] = (0, 30),
    rotation_step: int = 45,
    blocked: tuple[tuple[int, int], ...] = ((0, 3),),
    seed: int = 0,
    scene: str = "FloorPlan5",
    room_type: str = "kitchen",
) -> SceneData:
    """A SceneData on the given grid positions (default: a 2x2 grid), every yaw and horizon.

    MoveAhead follows the SAVN rule (diagonals move by (+-0.25, +-0.25)) and fails off the grid
    or across a ``blocked`` position pair (here the diagonal 0 -> 3). In-view entries, boxes,
    visibility and uint8 features are random but seeded.
    """
    rng = np.random.default_rng(seed)
    yaws = list(range(0, 360, rotation_step))
    poses = [(p, y, h) for p in range(len(positions)) for y in yaws for h in horizons]
    index = {pose: i for i, pose in enumerate(poses)}
    cell = {(round(x / 0.25), round(z / 0.25)): i for i, (x, z) in enumerate(positions)}
    blocked_pairs = {frozenset(b) for b in blocked}
    n = len(poses)
    successors = np.tile(np.arange(n, dtype=np.int32)[:, None], (1, N_MOVEMENT_ACTIONS))
    for i, (p, y, h) in enumerate(poses):
        x, z = positions[p]
        sx, sz = round(math.sin(math.radians(y))), round(math.cos(math.radians(y)))
        dest = cell.get((round(x / 0.25) + sx, round(z / 0.25) + sz))
        if dest is not None and frozenset((p, dest)) not in blocked_pairs:
            successors[i, 0] = index[(dest, y, h)]
        successors[i, 1] = index[(p, (y - rotation_step) % 360, h)]
        successors[i, 2] = index[(p, (y + rotation_step) % 360, h)]
        k = horizons.index(h)
        if k > 0:
            successors[i, 3] = index[(p, y, horizons[k - 1])]
        if k < len(horizons) - 1:
            successors[i, 4] = index[(p, y, horizons[k + 1])]

    categories = category_set("mjolnir101")
    types = tuple(t for _, t in INSTANCES)
    rows = category_rows(types, "mjolnir101")
    view_ptr = np.zeros(n + 1, dtype=np.int64)
    inst_list, box_list, vis_list = [], [], []
    context = np.zeros((n, len(categories), 4), dtype=np.float32)
    for i in range(n):
        in_view = np.flatnonzero(rng.random(len(INSTANCES) - 1) < 0.5)  # Apple (last but one)...
        in_view = in_view[in_view != 5]  # ...is never in view
        x1 = rng.uniform(0, 200, len(in_view))
        y1 = rng.uniform(0, 200, len(in_view))
        boxes = np.stack(
            [x1, y1, x1 + rng.uniform(1, 100, len(in_view)), y1 + rng.uniform(1, 100, len(in_view))], axis=1
        ).astype(np.float32)
        visible = rng.random(len(in_view)) < 0.6
        view_ptr[i + 1] = view_ptr[i] + len(in_view)
        inst_list.append(in_view)
        box_list.append(boxes)
        vis_list.append(visible)
        context[i] = context_from_boxes(rows[in_view], boxes, len(categories))
    features = rng.integers(0, 256, (n, len(categories) + 3, 7, 7), dtype=np.uint8)
    return SceneData(
        scene=scene,
        room_type=room_type,
        x=np.array([positions[p][0] for p, _, _ in poses], dtype=np.float32),
        z=np.array([positions[p][1] for p, _, _ in poses], dtype=np.float32),
        yaw=np.array([y for _, y, _ in poses], dtype=np.int16),
        horizon=np.array([h for _, _, h in poses], dtype=np.int16),
        successors=successors,
        instance_ids=tuple(i for i, _ in INSTANCES),
        instance_types=types,
        view_ptr=view_ptr,
        view_instance=np.concatenate(inst_list).astype(np.int32),
        view_box=np.concatenate(box_list).reshape(-1, 4),
        view_distance=rng.uniform(0.2, 3.0, int(view_ptr[-1])).astype(np.float32),
        view_visible=np.concatenate(vis_list),
        context=context,
        features=features,
        meta={"backend": "fixture", "category_set": "mjolnir101"},
    )
