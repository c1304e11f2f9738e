"""Shared vocabulary of the SAVN/MJOLNIR offline scene format.

One folder per scene holds ``graph.json`` (networkx node-link ``DiGraph`` of pose keys, edges under
``links``), ``grid.json`` (reachable positions), ``visible_object_map.json`` (object id -> pose keys
where it is visible), ``objects_bb.json`` (pose key -> object type -> flattened 2-D boxes; MJOLNIR
only) and ``resnet18_featuremap.hdf5`` (one dataset per pose key: ``(1, 512, 7, 7)`` in SAVN,
``(512, 7, 7)`` in MJOLNIR). See ../shared/docs/reference-implementations.md §1.

The transition rule of the originals is reproduced here: the next pose of an action is guessed
geometrically, as a key string, and the action succeeds iff that string is a successor of the
current pose in ``graph.json``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from mapless.actions import LOOK_DOWN, LOOK_UP, MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT
from mapless.errors import MaplessError
from mapless.sim.context import context_from_boxes  # noqa: F401 - re-exported for the reader

FORMATS: tuple[str, ...] = ("savn", "mjolnir")
GRAPH_FILE = "graph.json"
GRID_FILE = "grid.json"
VISIBLE_FILE = "visible_object_map.json"
BOXES_FILE = "objects_bb.json"
FEATURES_FILE = "resnet18_featuremap.hdf5"
IMAGES_FILE = "images.hdf5"
#: mapless' own side file: ignored by the original code bases, it lets the reader undo the
#: 512-channel zero padding of exported semantic features and skip alias box keys.
SIDE_FILE = "mapless.json"
RESNET_CHANNELS = 512
FEATURE_SIDE = 7
IMAGE_SIZE = 300
HORIZON_STEP = 30
DEFAULT_AGENT_Y = 0.9009997  # AI2-THOR default agent capsule centre height (m)


class OfflineFormatError(MaplessError):
    """A scene folder or episode file that does not follow the SAVN/MJOLNIR format."""

    def __init__(self, path: object, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = path, problem


def check_format(name: str) -> str:
    if name not in FORMATS:
        from mapless.errors import UnknownNameError

        raise UnknownNameError("offline format", name, FORMATS)
    return name


def scene_folder_name(scene: str, format: str) -> str:
    """Folder name the original code base expects: SAVN appends ``_physics`` to kitchens and
    living rooms only (its name builder strips it for 3xx/4xx); MJOLNIR never does."""
    from mapless.scenes.catalogue import canonical_scene

    check_format(format)
    try:
        name = canonical_scene(scene)
    except MaplessError:
        return scene  # a user's own scene name: keep it verbatim
    number = int(name.removeprefix("FloorPlan"))
    return f"{name}_physics" if format == "savn" and number < 300 else name


def parse_pose_key(key: str) -> tuple[float, float, int, int]:
    """``"x|z|rotation|horizon"`` -> (x, z, rotation, horizon); raises ``ValueError`` if malformed."""
    problem = f"pose key {key!r} is not 'x|z|rotation|horizon'"
    parts = key.split("|")
    if len(parts) != 4:
        raise ValueError(problem)
    try:
        x, z, rotation, horizon = (float(p) for p in parts)
    except ValueError:
        raise ValueError(problem) from None
    if not (math.isfinite(x) and math.isfinite(z) and rotation.is_integer() and horizon.is_integer()):
        raise ValueError(problem)
    return x, z, int(rotation), int(horizon)


def object_type_of_id(object_id: str) -> str:
    """Type of a THOR object id ``Type|x|y|z``; sub-objects append their own type
    (``Sink|-03.12|-00.01|+01.53|SinkBasin`` is a ``SinkBasin``)."""
    parts = object_id.split("|")
    return parts[-1] if len(parts) > 4 and parts[-1].isalpha() else parts[0]


def _signed_horizon(horizon: int) -> int:
    # Some THOR versions report looking up as 330 instead of -30.
    return horizon - 360 if horizon > 180 else horizon


def guess_next_keys(
    key: str, action: int, grid_size: float = 0.25, rotation_step: int = 45, horizon_step: int = HORIZON_STEP
) -> tuple[str, ...]:
    """Key strings the original controller would look for after a movement action.

    Unchanged coordinates keep their exact text (so a ``-0.00`` stays ``-0.00``, as it does in the
    original, which only adds to the coordinate that moves). Looks return both the signed and the
    modulo-360 horizon spelling, since data sets disagree on it.
    """
    xs, zs, rot, hor = key.split("|")
    yaw, horizon = int(float(rot)), _signed_horizon(int(float(hor)))
    if action == MOVE_AHEAD:
        rad = math.radians(yaw)
        sx, sz = round(math.sin(rad)), round(math.cos(rad))
        x = xs if sx == 0 else f"{float(xs) + sx * grid_size:.2f}"
        z = zs if sz == 0 else f"{float(zs) + sz * grid_size:.2f}"
        return (f"{x}|{z}|{rot}|{hor}",)
    if action in (ROTATE_LEFT, ROTATE_RIGHT):
        turn = -rotation_step if action == ROTATE_LEFT else rotation_step
        return (f"{xs}|{zs}|{(yaw + turn) % 360}|{hor}",)
    if action in (LOOK_UP, LOOK_DOWN):
        new = horizon - horizon_step if action == LOOK_UP else horizon + horizon_step
        return tuple(dict.fromkeys((f"{xs}|{zs}|{rot}|{new}", f"{xs}|{zs}|{rot}|{new % 360}")))
    raise ValueError(f"action {action} is not a movement action")


def infer_rotation_step(yaws: Iterable[int]) -> int:
    """The rotation step of a pose set: gcd of its yaws and 360 (45 for SAVN data)."""
    step = 360
    for yaw in set(yaws):
        step = math.gcd(step, int(yaw) % 360)
    return step


def category_rows(types: Iterable[str], category_set_name: str) -> np.ndarray:
    """Category row of each object type (-1 if none). Accepts AI2-THOR 5 type names and the v1
    names of the MJOLNIR list (``TableTop``...), since real MJOLNIR data uses the latter."""
    from mapless.scenes.categories import category_set

    categories = category_set(category_set_name)
    by_name = {name: i for i, name in enumerate(categories.names)}
    return np.array(
        [categories.type_to_index.get(t, by_name.get(t, -1)) for t in types], dtype=np.int64
    ).reshape(-1)
