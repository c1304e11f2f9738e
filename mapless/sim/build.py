"""Build a scene's :class:`SceneData` from its layout with the geometric simulator."""

from __future__ import annotations

import functools

import numpy as np

from mapless.actions import N_MOVEMENT_ACTIONS
from mapless.scenes.categories import category_set
from mapless.scenes.floor_plans import Scene
from mapless.sim.config import SimConfig
from mapless.sim.context import context_from_boxes
from mapless.sim.raycast import FLOOR, WALL, Frame, RayCaster
from mapless.sim.room import InteriorMask, obstacle_polygons, segment_hits_polygon
from mapless.sim.scene_data import SceneData

FEATURE_EXTRA_CHANNELS = 3  # floor, wall, depth
MAX_FEATURE_DEPTH = 10.0  # m, depth channel saturates here


def pose_ids(n_positions: int, config: SimConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position index, yaw index and horizon index of every pose id (position-major order)."""
    n_yaw, n_hor = len(config.yaws), len(config.horizons)
    ids = np.arange(n_positions * n_yaw * n_hor)
    return ids // (n_yaw * n_hor), (ids // n_hor) % n_yaw, ids % n_hor


def build_transitions(scene: Scene, config: SimConfig) -> np.ndarray:
    """``[P, 5]`` successor table. MoveAhead moves one grid step along the heading, diagonals by
    (+-g, +-g); it fails when the destination is not on the reachable grid or the segment crosses
    an obstacle footprint (``strict_diagonals``: or a diagonal step's orthogonal neighbour is off
    the grid). Rotations wrap; looks fail at the ends of the horizon list."""
    positions = scene.reachable
    n_pos, n_yaw, n_hor = len(positions), len(config.yaws), len(config.horizons)
    g = config.grid_size
    cell = {(round(x / g), round(z / g)): i for i, (x, z) in enumerate(positions)}
    polygons = obstacle_polygons(scene, config.obstacle_margin)
    pos_i, yaw_i, hor_i = pose_ids(n_pos, config)

    def pid(p: int, y: int, h: int) -> int:
        return (p * n_yaw + y) * n_hor + h

    @functools.cache
    def move_destination(p: int, y: int) -> int | None:
        """Grid point reached by MoveAhead from position ``p`` at yaw index ``y`` (None: blocked)."""
        yaw = np.radians(config.yaws[y])
        step = (int(np.round(np.sin(yaw))), int(np.round(np.cos(yaw))))
        x, z = positions[p]
        i, j = round(x / g), round(z / g)
        dest = cell.get((i + step[0], j + step[1]))
        # The strict rule: a diagonal step passes between two orthogonal neighbours; one off the grid
        # is a wall or counter corner the agent would bump into.
        corner = (i + step[0], j) not in cell or (i, j + step[1]) not in cell
        if dest is not None and config.strict_diagonals and all(step) and corner:
            return None
        if dest is not None and any(
            segment_hits_polygon(positions[p], positions[dest], poly) for poly in polygons
        ):
            return None
        return dest

    succ = np.empty((len(pos_i), N_MOVEMENT_ACTIONS), dtype=np.int32)
    for pose, (p, y, h) in enumerate(zip(pos_i, yaw_i, hor_i, strict=True)):
        dest = move_destination(int(p), int(y))
        succ[pose, 0] = pose if dest is None else pid(dest, y, h)
        succ[pose, 1] = pid(p, (y - 1) % n_yaw, h)
        succ[pose, 2] = pid(p, (y + 1) % n_yaw, h)
        succ[pose, 3] = pid(p, y, h - 1) if h > 0 else pose
        succ[pose, 4] = pid(p, y, h + 1) if h < n_hor - 1 else pose
    return succ


def _capsule_distance(points: np.ndarray, x: float, z: float, eye_height: float) -> np.ndarray:
    """AI2-THOR's visibility capsule: distance to the vertical segment from the floor to the eye."""
    horizontal = np.hypot(points[:, 0] - x, points[:, 2] - z)
    above = np.maximum(points[:, 1] - eye_height, 0.0)
    return np.hypot(horizontal, above)


def build_scene_data(scene: Scene, config: SimConfig, progress: bool = False) -> SceneData:
    categories = category_set(config.category_set)
    n_cat = len(categories)
    cat_of_instance = np.array([categories.type_to_index.get(o.type, -1) for o in scene.objects])
    hidden = np.array([scene.inside_closed_receptacle(i) for i in range(len(scene.objects))], dtype=bool)

    positions = scene.reachable
    interior = InteriorMask(scene, config.wall_clearance)
    walls = interior.wall_distances(positions)
    caster = RayCaster(scene, config)
    pos_i, yaw_i, hor_i = pose_ids(len(positions), config)
    n_poses = len(pos_i)
    res = config.ray_resolution
    cell = res // 7
    scale = config.image_size / res
    cell_of_ray = ((np.arange(res * res) // res) // cell) * 7 + (np.arange(res * res) % res) // cell

    context = np.zeros((n_poses, n_cat, 4), dtype=np.float32)
    features = np.zeros((n_poses, n_cat + FEATURE_EXTRA_CHANNELS, 49), dtype=np.uint8)
    view_ptr = np.zeros(n_poses + 1, dtype=np.int64)
    view_chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    iterator = range(n_poses)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=scene.name, leave=False, unit="pose")
    for pose in iterator:
        x, z = positions[pos_i[pose]]
        frame = caster.render(
            x, z, config.yaws[yaw_i[pose]], config.horizons[hor_i[pose]], walls[pos_i[pose]]
        )
        inst, boxes, dist = _instances_in_frame(frame, res, scale, x, z, config.eye_height)
        visible = (dist <= config.visibility_distance) & ~hidden[inst]
        view_chunks.append((inst, boxes, dist, visible))
        view_ptr[pose + 1] = view_ptr[pose] + len(inst)
        context[pose] = context_from_boxes(cat_of_instance[inst], boxes, n_cat, config.image_size)
        features[pose] = _feature_map(frame, cat_of_instance, n_cat, cell_of_ray, cell * cell)

    view_inst, view_box, view_dist, view_vis = (
        np.concatenate([c[i] for c in view_chunks]) if view_chunks else np.zeros(0) for i in range(4)
    )
    return SceneData(
        scene=scene.name,
        room_type=scene.room_type,
        x=positions[pos_i, 0].astype(np.float32),
        z=positions[pos_i, 1].astype(np.float32),
        yaw=np.asarray(config.yaws, dtype=np.int16)[yaw_i],
        horizon=np.asarray(config.horizons, dtype=np.int16)[hor_i],
        successors=build_transitions(scene, config),
        instance_ids=tuple(o.id for o in scene.objects),
        instance_types=tuple(o.type for o in scene.objects),
        view_ptr=view_ptr,
        view_instance=view_inst.astype(np.int32),
        view_box=view_box.astype(np.float32).reshape(-1, 4),
        view_distance=view_dist.astype(np.float32),
        view_visible=view_vis.astype(bool),
        context=context,
        features=features.reshape(n_poses, -1, 7, 7),
        meta={"backend": "geometric", "category_set": config.category_set},
    )


def _instances_in_frame(
    frame: Frame, res: int, scale: float, x: float, z: float, eye_height: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Instances hit by at least one ray, their pixel boxes in the full frame and rule distance."""
    hit = frame.ids >= 0
    if not hit.any():
        return np.zeros(0, np.int32), np.zeros((0, 4)), np.zeros(0)
    rays = np.flatnonzero(hit)
    ids = frame.ids[rays]
    inst, inverse = np.unique(ids, return_inverse=True)
    rows, cols = rays // res, rays % res
    boxes = np.empty((len(inst), 4))
    for column, values, reducer in ((0, cols, np.minimum), (1, rows, np.minimum)):
        acc = np.full(len(inst), res, dtype=np.int64)
        reducer.at(acc, inverse, values)
        boxes[:, column] = acc * scale
    for column, values in ((2, cols), (3, rows)):
        acc = np.full(len(inst), -1, dtype=np.int64)
        np.maximum.at(acc, inverse, values)
        boxes[:, column] = (acc + 1) * scale
    dist = np.full(len(inst), np.inf)
    np.minimum.at(dist, inverse, _capsule_distance(frame.points[rays], x, z, eye_height))
    return inst.astype(np.int32), boxes, dist


def _feature_map(
    frame: Frame, cat_of_instance: np.ndarray, n_cat: int, cell_of_ray: np.ndarray, rays_per_cell: int
) -> np.ndarray:
    """``[C + 3, 49]`` uint8: per-cell coverage of each category, floor and wall, and mean depth."""
    channel = np.where(frame.ids >= 0, cat_of_instance[np.maximum(frame.ids, 0)], -1)
    channel = np.where(frame.ids == FLOOR, n_cat, np.where(frame.ids == WALL, n_cat + 1, channel))
    valid = channel >= 0
    counts = np.bincount(channel[valid] * 49 + cell_of_ray[valid], minlength=(n_cat + 2) * 49)
    out = np.empty((n_cat + 3, 49), dtype=np.uint8)
    out[: n_cat + 2] = np.round(counts.reshape(n_cat + 2, 49) * (255.0 / rays_per_cell))
    depth = np.bincount(cell_of_ray, weights=np.minimum(frame.depth, MAX_FEATURE_DEPTH), minlength=49)
    out[n_cat + 2] = np.round(depth / rays_per_cell / MAX_FEATURE_DEPTH * 255)
    return out
