"""Read a SAVN/MJOLNIR offline scene folder into a :class:`SceneData`.

Everything is validated at load time (missing files, malformed JSON/HDF5, poses of the graph
without a feature map), so a bad folder fails before training starts, never mid-episode.

What the format does not carry, and how it is filled in:

* ``view_distance``: not recorded by the originals (visibility is baked into
  ``visible_object_map.json``), so it is NaN.
* Boxes are stored per object *type*, not per instance. Boxes of a type are attributed to the
  visible instances of that type in order (the order mapless' writer uses, so exported scenes
  read back exactly); boxes left over belong to instances in view but not visible, which the
  format cannot name: they become entries of one ``"<Type>|unattributed"`` instance per type,
  never visible, so they count for the context vector but never for success.
* SAVN folders have no ``objects_bb.json``: visible instances are then in view with zero boxes
  (``meta["has_boxes"]`` is False) and only the context's in-view flag is meaningful.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mapless.actions import N_MOVEMENT_ACTIONS
from mapless.errors import MaplessError, UnknownNameError
from mapless.offline.format import (
    BOXES_FILE,
    FEATURE_SIDE,
    FEATURES_FILE,
    GRAPH_FILE,
    GRID_FILE,
    SIDE_FILE,
    VISIBLE_FILE,
    OfflineFormatError,
    category_rows,
    context_from_boxes,
    guess_next_keys,
    infer_rotation_step,
    object_type_of_id,
    parse_pose_key,
)
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import SceneData, pose_key

FEATURE_MODES = ("auto", "resnet", "none")
UNATTRIBUTED = "unattributed"


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise OfflineFormatError(path, "missing (required by the SAVN/MJOLNIR offline format)")
    try:
        with path.open("rb") as f:
            return json.load(f)
    except json.JSONDecodeError as error:
        raise OfflineFormatError(path, f"malformed JSON ({error})") from None
    except RecursionError:
        raise OfflineFormatError(path, "malformed JSON (nested too deeply)") from None
    except (OSError, UnicodeDecodeError) as error:
        raise OfflineFormatError(path, f"cannot be read ({error})") from None


_SIDE_DTYPES = ("uint8", "int8", "uint16", "int16", "float16", "float32", "float64")
#: Fields of mapless' side file and the check each value must pass.
_SIDE_FIELDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "feature_kind": (lambda v: isinstance(v, str), "a string"),
    "feature_channels": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a count >= 0"),
    "feature_scale": (
        lambda v: isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) and v > 0,
        "a positive number",
    ),
    "features_dtype": (lambda v: v in _SIDE_DTYPES, f"one of {', '.join(_SIDE_DTYPES)}"),
    "alias_types": (lambda v: isinstance(v, list) and all(isinstance(t, str) for t in v), "a list of types"),
    "scene": (lambda v: isinstance(v, str), "a string"),
    "room_type": (lambda v: isinstance(v, str), "a string"),
}


def _side_file(path: Path) -> dict:
    """mapless' side file (:data:`SIDE_FILE`), each known field checked: its values size and type
    the feature array, so a bad one must be an error naming the file, not a numpy traceback."""
    if not path.is_file():
        return {}
    side = _read_json(path)
    if not isinstance(side, dict):
        raise OfflineFormatError(path, "expected a JSON object")
    for key, (valid, expected) in _SIDE_FIELDS.items():
        if key in side and not valid(side[key]):
            raise OfflineFormatError(path, f"{key} {side[key]!r} is not {expected}")
    if side.get("feature_kind") == "semantic":
        missing = [k for k in ("feature_channels", "feature_scale", "features_dtype") if k not in side]
        if missing:
            raise OfflineFormatError(path, f"semantic features need {', '.join(missing)}")
    return side


def _graph(path: Path) -> tuple[list[str], list[set[int]]]:
    """Node keys in file order and the successor index sets of each node."""
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("nodes"), list):
        raise OfflineFormatError(path, "not networkx node-link data (no 'nodes' list)")
    # networkx < 3.4 (the originals) writes 'links'; newer versions may write 'edges'.
    links = data.get("links", data.get("edges"))
    if not isinstance(links, list):
        raise OfflineFormatError(path, "not networkx node-link data (no 'links' or 'edges' list)")
    keys: list[str] = []
    for i, node in enumerate(data["nodes"]):
        if not isinstance(node, dict) or not isinstance(node.get("id"), str):
            raise OfflineFormatError(path, f"node {i} has no string 'id'")
        try:
            parse_pose_key(node["id"])
        except ValueError as error:
            raise OfflineFormatError(path, f"node {i}: {error}") from None
        keys.append(node["id"])
    index = {k: i for i, k in enumerate(keys)}
    if len(index) != len(keys):
        raise OfflineFormatError(path, "duplicate node ids")
    successors: list[set[int]] = [set() for _ in keys]
    # The originals call .to_directed(): an undirected file means every edge both ways.
    both_ways = not data.get("directed", True)
    for i, link in enumerate(links):
        try:
            s, t = index[link["source"]], index[link["target"]]
        except (KeyError, TypeError):
            raise OfflineFormatError(path, f"link {i} ({link!r}) does not join two nodes") from None
        successors[s].add(t)
        if both_ways:
            successors[t].add(s)
    return keys, successors


def _grid(path: Path) -> list[dict]:
    grid = _read_json(path)
    if not isinstance(grid, list) or not grid:
        raise OfflineFormatError(path, "expected a non-empty list of {x, y, z} positions")
    for i, point in enumerate(grid):
        if not isinstance(point, dict) or not all(isinstance(point.get(c), int | float) for c in "xz"):
            raise OfflineFormatError(path, f"entry {i} ({point!r}) is not an {{x, y, z}} position")
    return grid


def _visible_map(path: Path, index: dict[str, int]) -> tuple[list[str], list[list[int]], int]:
    """Object ids and, per object, the pose indices where it is visible. Accepts SAVN's
    ``visible_object_map.json`` and the pose-keyed raw ``metadata.json`` the originals also read."""
    data = _read_json(path)
    if not isinstance(data, dict):
        raise OfflineFormatError(path, "expected a JSON object {objectId: [pose keys]}")
    first = next(iter(data), None)
    pose_keyed = first is not None and _is_pose_key(first)
    objects: dict[str, list[int]] = {}
    unknown = 0
    if pose_keyed:
        for key, metadata in data.items():
            rows = metadata.get("objects") if isinstance(metadata, dict) else None
            if not isinstance(rows, list):
                raise OfflineFormatError(path, f"pose {key!r} has no 'objects' list")
            if key not in index:
                unknown += 1
                continue
            for row in rows:
                if not isinstance(row, dict) or not isinstance(row.get("objectId"), str):
                    raise OfflineFormatError(path, f"pose {key!r}: an object has no 'objectId'")
                if row.get("visible"):
                    objects.setdefault(row["objectId"], []).append(index[key])
    else:
        for object_id, keys in data.items():
            if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
                raise OfflineFormatError(path, f"{object_id!r} is not mapped to a list of pose keys")
            poses = []
            for key in keys:
                if key in index:
                    poses.append(index[key])
                else:
                    unknown += 1
            objects[object_id] = poses
    return list(objects), list(objects.values()), unknown


def _is_pose_key(text: str) -> bool:
    try:
        parse_pose_key(text)
    except ValueError:
        return False
    return True


def _boxes(path: Path, index: dict[str, int]) -> tuple[dict[int, dict[str, np.ndarray]], int]:
    data = _read_json(path)
    if not isinstance(data, dict):
        raise OfflineFormatError(path, "expected a JSON object {pose key: {objectType: [boxes]}}")
    out: dict[int, dict[str, np.ndarray]] = {}
    unknown = 0
    for key, by_type in data.items():
        if not isinstance(by_type, dict):
            raise OfflineFormatError(path, f"pose {key!r}: expected {{objectType: [x1, y1, x2, y2, ...]}}")
        if key not in index:
            unknown += 1
            continue
        row: dict[str, np.ndarray] = {}
        for object_type, flat in by_type.items():
            numbers = isinstance(flat, list) and all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in flat
            )
            values = np.asarray(flat, dtype=np.float64) if numbers else None
            if values is None or not np.isfinite(values).all() or len(values) % 4:
                raise OfflineFormatError(
                    path,
                    f"pose {key!r}, {object_type!r}: boxes must be a flat list of finite numbers, 4 per box",
                )
            row[object_type] = values.reshape(-1, 4)
        out[index[key]] = row
    return out, unknown


def _features(
    path: Path, keys: list[str], mode: str, side: dict, dtype: np.dtype
) -> tuple[np.ndarray, float, str]:
    """``[P, F, 7, 7]`` features of the graph poses, their scale and kind."""
    if mode == "none":
        return np.zeros((len(keys), 0, FEATURE_SIDE, FEATURE_SIDE), dtype=np.uint8), 1.0, "none"
    import h5py

    if not path.is_file():
        raise OfflineFormatError(path, "missing (required by the SAVN/MJOLNIR offline format)")
    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise OfflineFormatError(path, f"not a readable HDF5 file ({error})") from None
    try:
        with f:
            return _read_features(f, path, keys, mode, side, dtype)
    except MaplessError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, MemoryError) as error:
        # h5py's errors on a damaged file (a broken B-tree, a link past the end, absurd sizes, ...)
        raise OfflineFormatError(path, f"damaged HDF5 file ({type(error).__name__}: {error})") from None


def _read_features(
    f: Any, path: Path, keys: list[str], mode: str, side: dict, dtype: np.dtype
) -> tuple[np.ndarray, float, str]:
    import h5py

    missing = [k for k in keys if k not in f]
    if missing:
        raise OfflineFormatError(
            path,
            f"{len(missing)} of the {len(keys)} poses of {GRAPH_FILE} have no feature map "
            f"(first: {', '.join(repr(k) for k in missing[:3])})",
        )
    first = f[keys[0]]
    shape = getattr(first, "shape", None)
    if shape is None or not (
        len(shape) in (3, 4)
        and shape[-2:] == (FEATURE_SIDE, FEATURE_SIDE)
        and (len(shape) == 3 or shape[0] == 1)
    ):
        raise OfflineFormatError(
            path,
            f"dataset {keys[0]!r} has shape {shape}; expected (1, C, 7, 7) (SAVN) or (C, 7, 7) (MJOLNIR)",
        )
    semantic = mode == "auto" and side.get("feature_kind") == "semantic"
    if semantic:
        # mapless' own export: read only the real channels and re-quantise to the stored dtype.
        channels, scale = int(side["feature_channels"]), float(side["feature_scale"])
        stored = np.dtype(side["features_dtype"])
        if channels > shape[-3]:
            raise OfflineFormatError(
                path.with_name(SIDE_FILE),
                f"feature_channels {channels} exceeds the {shape[-3]} channels of {path.name}",
            )
    else:
        channels, scale, stored = shape[-3], 1.0, dtype
    out = np.empty((len(keys), channels, FEATURE_SIDE, FEATURE_SIDE), dtype=stored)
    selection = (0, slice(0, channels)) if len(shape) == 4 else (slice(0, channels),)
    for p, key in enumerate(keys):
        dataset = f[key]
        if not isinstance(dataset, h5py.Dataset):
            raise OfflineFormatError(path, f"{key!r} is a group, not a dataset")
        if dataset.shape != shape:
            raise OfflineFormatError(path, f"dataset {key!r} has shape {dataset.shape}, others {shape}")
        try:
            values = np.asarray(dataset[selection], dtype=np.float32)
        except (OSError, ValueError, TypeError) as error:
            raise OfflineFormatError(path, f"dataset {key!r} cannot be read ({error})") from None
        if semantic and np.issubdtype(stored, np.integer):
            info = np.iinfo(stored)
            values = np.clip(np.rint(values / scale), info.min, info.max)
        elif semantic:
            values = values / scale
        out[p] = values
    return out, scale, "semantic" if semantic else "resnet18"


def _successor_table(
    keys: list[str], index: dict[str, int], graph_successors: list[set[int]], grid_size: float, step: int
) -> np.ndarray:
    """``[P, movement actions]`` pose index each movement leads to (itself where the graph has no
    such edge): the graph stores edges without their action, so each action's expected key is
    guessed and kept when the graph has that edge."""
    successors = np.repeat(np.arange(len(keys), dtype=np.int32)[:, None], N_MOVEMENT_ACTIONS, axis=1)
    for p, key in enumerate(keys):
        out = graph_successors[p]
        if not out:
            continue
        for action in range(N_MOVEMENT_ACTIONS):
            for guess in guess_next_keys(key, action, grid_size, step):
                q = index.get(guess)
                if q is not None and q in out:
                    successors[p, action] = q
                    break
    return successors


def _views(
    n_poses: int,
    types: list[str],
    visible_poses: list[list[int]],
    boxes: dict[int, dict[str, np.ndarray]],
    alias_types: set[str],
) -> tuple[dict[str, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What each pose sees, as ``SceneData``'s flat view arrays: the file's boxes per type attributed
    to that type's visible instances in order, the rest to one never-visible ``unattributed``
    instance per type (numbered after the named ones). Returns those types (in order of first use)
    and ``view_ptr``, ``view_instance``, ``view_box``, ``view_visible``."""
    # Visible instances per pose, in instance order (= file order).
    visible_at: list[list[int]] = [[] for _ in range(n_poses)]
    for i, pose_list in enumerate(visible_poses):
        for p in sorted(set(pose_list)):
            visible_at[p].append(i)
    unattributed: dict[str, int] = {}
    entries: list[list[tuple[int, np.ndarray, bool]]] = []
    zero = np.zeros(4)
    for p in range(n_poses):
        row: list[tuple[int, np.ndarray, bool]] = []
        by_type: dict[str, list[int]] = {}
        for i in visible_at[p]:
            by_type.setdefault(types[i], []).append(i)
        pose_boxes = {t: b for t, b in boxes.get(p, {}).items() if t not in alias_types}
        for object_type in dict.fromkeys([*by_type, *pose_boxes]):
            seen = by_type.get(object_type, [])
            type_boxes = pose_boxes.get(object_type, np.zeros((0, 4)))
            for j, i in enumerate(seen):
                row.append((i, type_boxes[j] if j < len(type_boxes) else zero, True))
            if len(type_boxes) > len(seen):
                k = unattributed.setdefault(object_type, len(unattributed))
                row.extend((-1 - k, b, False) for b in type_boxes[len(seen) :])
        entries.append(row)
    # Unattributed instances go after the named ones (negative placeholders resolved here).
    n_named = len(types)
    view_ptr = np.zeros(n_poses + 1, dtype=np.int64)
    flat_inst, flat_box, flat_vis = [], [], []
    for p, row in enumerate(entries):
        resolved = sorted(
            (((i if i >= 0 else n_named - 1 - i), box, vis) for i, box, vis in row),
            key=lambda entry: entry[0],
        )
        view_ptr[p + 1] = view_ptr[p] + len(resolved)
        for i, box, vis in resolved:
            flat_inst.append(i)
            flat_box.append(box)
            flat_vis.append(vis)
    view_instance = np.asarray(flat_inst, dtype=np.int32)
    view_box = np.asarray(flat_box, dtype=np.float32).reshape(-1, 4)
    view_visible = np.asarray(flat_vis, dtype=bool)
    return unattributed, view_ptr, view_instance, view_box, view_visible


def load_offline_scene(
    folder: str | Path,
    category_set: str = "mjolnir101",
    features: str = "auto",
    *,
    feature_dtype: str = "float32",
    visible_file: str = VISIBLE_FILE,
    features_file: str = FEATURES_FILE,
    grid_size: float = 0.25,
    rotation_step: int | None = None,
    room_type: str | None = None,
) -> SceneData:
    """Load one SAVN/MJOLNIR scene folder.

    ``features``: ``"auto"`` (the HDF5 maps; exported mapless semantic maps are un-padded back to
    their ``F`` channels and stored dtype), ``"resnet"`` (all channels as stored, float) or
    ``"none"`` (no features, ``F = 0``: graph and visibility only). ``feature_dtype`` is the float
    dtype of loaded ResNet maps (``float16`` halves the ~100 kB per pose). ``visible_file`` may
    name HOZ's ``visible_object_map_1.5.json`` or a pose-keyed ``metadata.json``.
    ``rotation_step`` defaults to the gcd of the yaws present (45 for SAVN/MJOLNIR data).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise OfflineFormatError(folder, "not a directory")
    if features not in FEATURE_MODES:
        raise UnknownNameError("feature mode", features, FEATURE_MODES)
    side = _side_file(folder / SIDE_FILE)

    keys, graph_successors = _graph(folder / GRAPH_FILE)
    if not keys:
        raise OfflineFormatError(folder / GRAPH_FILE, "the graph has no nodes")
    grid = _grid(folder / GRID_FILE)
    index = {k: i for i, k in enumerate(keys)}
    poses = np.array([parse_pose_key(k) for k in keys], dtype=np.float64)
    for key, (x, z, yaw, horizon) in zip(keys, poses, strict=True):
        # Environments look poses up by SceneData.key(); it must reproduce the file's spelling.
        if pose_key(np.float32(x), np.float32(z), yaw, horizon) != key:
            raise OfflineFormatError(
                folder / GRAPH_FILE, f"pose key {key!r} is not in the 'x.xx|z.zz|rot|hor' form"
            )
    step = rotation_step or infer_rotation_step(poses[:, 2].astype(int))

    successors = _successor_table(keys, index, graph_successors, grid_size, step)

    object_ids, visible_poses, unknown_visible = _visible_map(folder / visible_file, index)
    boxes_path = folder / BOXES_FILE
    has_boxes = boxes_path.is_file()
    boxes, unknown_boxes = _boxes(boxes_path, index) if has_boxes else ({}, 0)
    for name, count in ((visible_file, unknown_visible), (BOXES_FILE, unknown_boxes)):
        if count:
            warnings.warn(
                f"{folder / name}: {count} pose keys are not nodes of {GRAPH_FILE}; ignored", stacklevel=2
            )
    types = [object_type_of_id(object_id) for object_id in object_ids]
    alias_types = set(side.get("alias_types", ()))
    unattributed, view_ptr, view_instance, view_box, view_visible = _views(
        len(keys), types, visible_poses, boxes, alias_types
    )
    instance_ids = tuple(object_ids) + tuple(f"{t}|{UNATTRIBUTED}" for t in unattributed)
    instance_types = tuple(types) + tuple(unattributed)

    rows = category_rows(instance_types, category_set)
    n_categories = _n_categories(category_set)
    context = np.zeros((len(keys), n_categories, 4), dtype=np.float32)
    for p in range(len(keys)):
        s = slice(view_ptr[p], view_ptr[p + 1])
        if s.start != s.stop:
            context[p] = context_from_boxes(rows[view_instance[s]], view_box[s], n_categories)

    feature_array, scale, kind = _features(
        folder / features_file, keys, features, side, np.dtype(feature_dtype)
    )
    scene, room = _scene_and_room(folder, side, room_type)
    agent_y = grid[0].get("y")
    return SceneData.from_poses(
        poses,
        scene=scene,
        room_type=room,
        successors=successors,
        instance_ids=instance_ids,
        instance_types=instance_types,
        view_ptr=view_ptr,
        view_instance=view_instance,
        view_box=view_box,
        view_distance=np.full(len(view_instance), np.nan, dtype=np.float32),
        view_visible=view_visible,
        context=context,
        features=feature_array,
        feature_scale=scale,
        meta={
            "backend": "offline",
            "source": str(folder),
            "category_set": category_set,
            "feature_kind": kind,
            "has_boxes": has_boxes,
            "agent_y": float(agent_y) if isinstance(agent_y, int | float) else None,
            "grid": [(float(g["x"]), float(g["z"])) for g in grid],
            "rotation_step": step,
            "unattributed_types": tuple(unattributed),
        },
    )


def _n_categories(name: str) -> int:
    from mapless.scenes.categories import category_set

    return len(category_set(name))


def _scene_and_room(folder: Path, side: dict, room_type: str | None) -> tuple[str, str]:
    from mapless.scenes.catalogue import ROOM_TYPES, canonical_scene, room_type_of

    name = folder.name
    try:
        scene = canonical_scene(side.get("scene", name))
        room = room_type_of(scene)
    except MaplessError:
        scene, room = side.get("scene", name), side.get("room_type", "unknown")
    if room_type is not None:
        if room_type not in ROOM_TYPES:
            raise UnknownNameError("room type", room_type, ROOM_TYPES)
        room = room_type
    return scene, room


def find_scene_folder(root: str | Path, scene: str) -> Path:
    """The folder of ``scene`` under an offline data root, whichever naming it uses
    (``FloorPlan1``, SAVN's ``FloorPlan1_physics``, or the name verbatim)."""
    root = Path(root)
    if not root.is_dir():
        raise OfflineFormatError(root, "no such offline data root (a folder of scene folders)")
    base = scene.removesuffix("_physics")
    for name in dict.fromkeys((scene, base, f"{base}_physics")):
        if (root / name / GRAPH_FILE).is_file():
            return root / name
    present = sorted(p.parent.name for p in root.glob(f"*/{GRAPH_FILE}"))
    raise UnknownNameError(f"scene folder in {root}", scene, present)


def offline_loader(root: str | Path, **kwargs: Any) -> Callable[[str], SceneData]:
    """``scene name -> SceneData`` over an offline data root (e.g. for ``SceneLibrary``);
    ``kwargs`` go to :func:`load_offline_scene`."""

    def load(scene: str) -> SceneData:
        return load_offline_scene(find_scene_folder(root, scene), **kwargs)

    return load


def offline_library(root: str | Path, category_set: str = "mjolnir101") -> SceneLibrary:
    """A :class:`~mapless.sim.library.SceneLibrary` of a SAVN/MJOLNIR offline data root (docs/guide/interop.md)."""
    return SceneLibrary(offline_loader(root, category_set=category_set))
