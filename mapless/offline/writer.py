"""Write a :class:`SceneData` as a SAVN/MJOLNIR offline scene folder.

The files are those the original controllers open (reference-implementations.md §1.1), so the
original code bases read an exported folder unchanged:

* ``graph.json``: node-link ``DiGraph`` with the edge list under ``links``; one edge per successful
  movement action. Every successor is checked against the originals' geometric guess first, so
  their transition rule reproduces ours exactly.
* ``grid.json``: the distinct reachable positions, ``y`` = the agent height.
* ``visible_object_map.json``: every instance visible from at least one pose (the originals only
  list those; an instance never visible would be an unreachable training target).
* ``objects_bb.json``: written for both formats (SAVN ignores it): every pose key, with the boxes
  of each in-view type, visible instances first, each group in instance order (the reader relies
  on that order). For MJOLNIR, types that AI2-THOR 5 renamed are also listed under their v1 name
  (``DiningTable``/``CoffeeTable`` boxes again under ``TableTop``...), so MJOLNIR's 101-object
  context vector finds them.
* ``resnet18_featuremap.hdf5``: our semantic map in place of ResNet-18 conv5: ``F`` channels
  (category coverage, floor, wall, depth; docs/guide/simulator.md, "Observations") as float32 values in [0, 1],
  zero-padded to 512 channels, shape ``(1, 512, 7, 7)`` (SAVN) or ``(512, 7, 7)`` (MJOLNIR).
* ``mapless.json``: our side file (ignored by the originals): scene, channel count, dtype and scale
  of the semantic map, alias types; the reader uses it to undo the padding.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mapless import __version__
from mapless.actions import ACTIONS, N_MOVEMENT_ACTIONS
from mapless.errors import MaplessError
from mapless.files import replacing, write_text
from mapless.offline.format import (
    BOXES_FILE,
    DEFAULT_AGENT_Y,
    FEATURE_SIDE,
    FEATURES_FILE,
    GRAPH_FILE,
    GRID_FILE,
    RESNET_CHANNELS,
    SIDE_FILE,
    VISIBLE_FILE,
    check_format,
    guess_next_keys,
    infer_rotation_step,
    scene_folder_name,
)
from mapless.scenes.categories import V1_TO_V5
from mapless.sim.scene_data import SceneData

#: AI2-THOR 5 type -> MJOLNIR v1 type name, for the renamed types that keep a v1 category.
V5_TO_V1: dict[str, str] = {v5: v1 for v1, v5s in V1_TO_V5.items() for v5 in v5s}


def check_transitions(scene_data: SceneData, keys: list[str], grid_size: float = 0.25) -> None:
    """Raise if some successful move is not what the originals' geometric guess would find."""
    index = {k: i for i, k in enumerate(keys)}
    step = infer_rotation_step(scene_data.yaw.tolist())
    bad = []
    for p, key in enumerate(keys):
        for action in range(N_MOVEMENT_ACTIONS):
            q = int(scene_data.successors[p, action])
            if q != p and keys[q] not in guess_next_keys(key, action, grid_size, step):
                bad.append(f"{ACTIONS[action]} from {key!r} leads to {keys[q]!r}")
        if len(bad) >= 3:
            break
    if bad:
        raise MaplessError(
            f"scene {scene_data.scene} cannot be exported: its transitions do not follow the SAVN "
            f"geometric rule ({'; '.join(bad)})"
        )
    if len(index) != len(keys):
        raise MaplessError(f"scene {scene_data.scene} cannot be exported: two poses share a key")


def export_scene(
    scene_data: SceneData,
    out_dir: str | Path,
    format: str = "savn",
    *,
    folder_name: str | None = None,
    compression: str | None = "gzip",
    v1_type_aliases: bool | None = None,
    grid_size: float = 0.25,
) -> Path:
    """Write ``scene_data`` to ``out_dir/<scene folder>/`` and return that folder.

    The folder name follows the format (``FloorPlan1_physics`` for SAVN kitchens and living rooms,
    ``FloorPlan1`` otherwise) unless ``folder_name`` is given. ``compression`` is an h5py filter
    for the feature file (``gzip`` is built into every HDF5, and the zero padding compresses to
    nearly nothing); ``None`` writes it uncompressed. ``v1_type_aliases`` defaults to True for
    MJOLNIR.
    """
    check_format(format)
    sd = scene_data
    n_channels = sd.features.shape[1]
    if n_channels > RESNET_CHANNELS:
        raise MaplessError(
            f"scene {sd.scene} has {n_channels} feature channels; the offline format holds at most "
            f"{RESNET_CHANNELS}"
        )
    if v1_type_aliases is None:
        v1_type_aliases = format == "mjolnir"
    keys = [sd.key(p) for p in range(sd.n_poses)]
    check_transitions(sd, keys, grid_size)

    folder = Path(out_dir) / (folder_name or scene_folder_name(sd.scene, format))
    folder.mkdir(parents=True, exist_ok=True)

    edges = sorted({(p, int(q)) for p in range(sd.n_poses) for q in sd.successors[p] if q != p})
    graph = {
        "directed": True,
        "multigraph": False,
        "graph": {},
        "nodes": [{"id": k} for k in keys],
        "links": [{"source": keys[s], "target": keys[t]} for s, t in edges],
    }
    agent_y = sd.meta.get("agent_y") or DEFAULT_AGENT_Y
    positions = dict.fromkeys((float(x), float(z)) for x, z in zip(sd.x, sd.z, strict=True))
    grid = [{"x": x, "y": agent_y, "z": z} for x, z in positions]

    visible: dict[str, list[str]] = {}
    boxes: dict[str, dict[str, list[float]]] = {}
    alias_types: set[str] = set()
    types = sd.instance_types
    for p, key in enumerate(keys):
        s = slice(sd.view_ptr[p], sd.view_ptr[p + 1])
        inst, box, vis = sd.view_instance[s], sd.view_box[s], sd.view_visible[s]
        for i in inst[vis]:
            visible.setdefault(sd.instance_ids[i], []).append(key)
        by_type: dict[str, list[float]] = {}
        # Visible instances first, then the others: the reader attributes boxes in this order.
        order = sorted(range(len(inst)), key=lambda j: (not vis[j], int(inst[j])))
        for j in order:
            by_type.setdefault(types[inst[j]], []).extend(map(float, box[j]))
        if v1_type_aliases:
            for object_type in list(by_type):
                alias = V5_TO_V1.get(object_type)
                if alias is not None and alias not in types:
                    by_type.setdefault(alias, []).extend(by_type[object_type])
                    alias_types.add(alias)
        boxes[key] = by_type
    # Instance order (the reader's attribution order), not first-seen order.
    visible = {i: visible[i] for i in sd.instance_ids if i in visible}

    _write_json(folder / GRAPH_FILE, graph)
    _write_json(folder / GRID_FILE, grid)
    _write_json(folder / VISIBLE_FILE, visible)
    _write_json(folder / BOXES_FILE, boxes)
    _write_features(folder / FEATURES_FILE, sd, keys, format, compression)
    side = {
        "mapless_version": __version__,
        "format": format,
        "scene": sd.scene,
        "room_type": sd.room_type,
        "feature_kind": sd.meta.get("feature_kind", "semantic"),
        "feature_channels": int(n_channels),
        "features_dtype": str(sd.features.dtype),
        "feature_scale": float(sd.feature_scale),
        "category_set": sd.meta.get("category_set"),
        "alias_types": sorted(alias_types),
        "box_order": "per type: visible instances first, then the other in-view ones, in instance order",
    }
    _write_json(folder / SIDE_FILE, side)
    return folder


def _write_json(path: Path, data: object) -> None:
    write_text(path, json.dumps(data, separators=(",", ":")))


def _write_features(path: Path, sd: SceneData, keys: list[str], format: str, compression: str | None) -> None:
    import h5py

    n_channels = sd.features.shape[1]
    shape = (
        (1, RESNET_CHANNELS, FEATURE_SIDE, FEATURE_SIDE)
        if format == "savn"
        else (RESNET_CHANNELS, FEATURE_SIDE, FEATURE_SIDE)
    )
    # Level 1: the zero padding compresses just as well, at a fraction of the default level's time.
    options = (
        {
            "compression": compression,
            "compression_opts": 1 if compression == "gzip" else None,
            "shuffle": True,
        }
        if compression
        else {}
    )
    padded = np.zeros((RESNET_CHANNELS, FEATURE_SIDE, FEATURE_SIDE), dtype=np.float32)
    with replacing(path) as tmp, h5py.File(tmp, "w") as f:
        for p, key in enumerate(keys):
            padded[:n_channels] = sd.features[p].astype(np.float32) * np.float32(sd.feature_scale)
            f.create_dataset(key, data=padded.reshape(shape), **options)
