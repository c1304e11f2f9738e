"""Category graphs: the Visual-Genome prior, its purified + hierarchical version, normalisation.

* ``vg``: MJOLNIR's prior, ``A[i, j] = 1`` iff the Visual-Genome relation count between categories i
  and j is >= 5 (``kg_prep/make_adjacency.py``), directed as shipped, self-loops only where VG had them
  (614 edges, 54 self-loops, 22 empty rows for ``mjolnir101``). Used by ``mjolnir_o/_r`` (faithful) and
  by ``sp``/``gve`` (their own 83-node SAVN graph does not match the category set; docs/guide/models.md).
* ``hierarchical``: the paper's "purified" graph augmented with parent edges:

  1. symmetrise the VG graph (VG's direction is the grammatical subject of a caption, not a property
     of the scene);
  2. purify: keep an edge only if both categories occur together in at least one *training* floor
     plan (drops caption co-occurrences that iTHOR never stages, e.g. bathroom--kitchen pairs, and every
     edge of a category absent from training);
  3. add a self-loop on every node (so the 22 nodes without VG edges still keep their own features);
  4. add symmetric target<->parent edges for every (room type, target, parent) of
     :func:`mapless.knowledge.parents.parent_lists` whose target belongs to :data:`GRAPH_TARGET_SETS`
     or to the run's own target set (optionally only for some room types, the paper's "no
     relationships" ablation).

:func:`normalize_adjacency` is the references' ``D^-1/2 A^T D^-1/2`` (row sums, inf -> 0).
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import numpy as np

from mapless.errors import UnknownNameError
from mapless.scenes.catalogue import ROOM_TYPES, scene_names
from mapless.scenes.categories import CATEGORY_SETS, category_set, targets

VG_FILES = {
    "mjolnir101": "priors/mjolnir_v1_weighted_adjacency_101_RAW.json",
    "all_types": "priors/thorv3_vg_adjacency_114.json",
}
VG_MIN_COUNT = 5
GRAPHS = ("vg", "hierarchical")
#: Target sets whose parent lists add the hierarchical graph's target<->parent edges in every run,
#: whatever its ``env.target_set``: the graph every run was trained with before ``hoz22`` came. A run
#: on another target set adds its own set's edges too (``target_set`` below; the trainer passes the
#: run's): hoz22 adds 21 (room type, target) pairs to mjolnir22's and SAVN's (Pan, Kettle, Plate in
#: kitchens, Book in living rooms, ...), 36 more non-zeros, in hoz22 runs only. The graph is a
#: trained parameter (the references'), so evaluation reads it from the
#: checkpoint whatever graph a fresh model starts with.
GRAPH_TARGET_SETS = ("mjolnir22", "savn")


@functools.cache
def vg_adjacency(set_name: str = "mjolnir101") -> np.ndarray:
    """``[C, C]`` float32 0/1 Visual-Genome prior over the set's categories (row/col = category order)."""
    if set_name not in VG_FILES:
        raise UnknownNameError("category set", set_name, CATEGORY_SETS)
    raw = json.loads(resources.files("mapless.data").joinpath(VG_FILES[set_name]).read_text())
    names = category_set(set_name).names
    if set_name == "mjolnir101":
        # MJOLNIR's weighted counts are stored in all_objects_v1 order, which is the category order.
        adjacency = (np.asarray(raw["weighted_adjacency"]) >= VG_MIN_COUNT).astype(np.float32)
    else:
        # The v3 fork's graph is already thresholded; map its 114 nodes onto the v5 types by name
        # (types the fork lacks keep no prior edges).
        source = np.asarray(raw["adjacency"], dtype=np.float32)
        where = {n: i for i, n in enumerate(raw["objects"])}
        rows = [where.get(n, -1) for n in names]
        adjacency = np.zeros((len(names), len(names)), np.float32)
        for a, ra in enumerate(rows):
            for b, rb in enumerate(rows):
                if ra >= 0 and rb >= 0:
                    adjacency[a, b] = source[ra, rb] > 0
    adjacency.setflags(write=False)
    return adjacency


@functools.cache
def training_cooccurrence(set_name: str = "mjolnir101") -> np.ndarray:
    """``[C, C]`` bool: both categories occur in at least one training floor plan."""
    cats = category_set(set_name)
    from mapless.scenes.layout import load_scene

    together = np.zeros((len(cats), len(cats)), dtype=bool)
    for name in scene_names("train"):
        present = np.zeros(len(cats), dtype=bool)
        for obj in load_scene(name).objects:
            index = cats.type_to_index.get(obj.type)
            if index is not None:
                present[index] = True
        together |= present[:, None] & present[None, :]
    return together


@functools.cache
def hierarchical_adjacency(
    set_name: str = "mjolnir101", rooms: tuple[str, ...] = ROOM_TYPES, target_set: str | None = None
) -> np.ndarray:
    """``[C, C]`` float32 0/1: purified, self-looped VG graph plus target<->parent edges of ``rooms``,
    for the targets of :data:`GRAPH_TARGET_SETS` and of ``target_set`` (a run's ``env.target_set``).

    Leaving a room type out of ``rooms`` (the Table 3 ablation) removes only the edges its hierarchy
    alone adds: pairs the VG graph or another room type also links stay (docs/guide/evaluation.md)."""
    from mapless.knowledge.parents import parent_lists

    for room in rooms:
        if room not in ROOM_TYPES:
            raise UnknownNameError("room type", room, ROOM_TYPES)
    cats = category_set(set_name)
    vg = vg_adjacency(set_name) > 0
    adjacency = (vg | vg.T) & training_cooccurrence(set_name)
    np.fill_diagonal(adjacency, True)
    lists = parent_lists(set_name)
    target_sets = GRAPH_TARGET_SETS + ((target_set,) if target_set else ())
    for room in rooms:
        graph_targets = {t for name in target_sets for t in targets(name)[room]}
        for target, entries in lists[room].items():
            if target not in graph_targets:
                continue
            t = cats.index(target)
            for entry in entries:
                p = cats.index(entry["parent"])
                adjacency[t, p] = adjacency[p, t] = True
    result = adjacency.astype(np.float32)
    result.setflags(write=False)
    return result


def category_graph(
    name: str,
    set_name: str = "mjolnir101",
    rooms: tuple[str, ...] = ROOM_TYPES,
    target_set: str | None = None,
) -> np.ndarray:
    """A graph of :data:`GRAPHS` by name (``rooms`` and ``target_set`` only affect ``hierarchical``)."""
    if name == "vg":
        return vg_adjacency(set_name)
    if name == "hierarchical":
        return hierarchical_adjacency(set_name, tuple(rooms), target_set)
    raise UnknownNameError("graph", name, GRAPHS)


def normalize_adjacency(adjacency: np.ndarray) -> np.ndarray:
    """``D^-1/2 A^T D^-1/2`` with ``D = diag(row sums of A)`` and isolated nodes left at 0 (as SAVN/MJOLNIR)."""
    adjacency = np.asarray(adjacency, dtype=np.float64)
    degree = adjacency.sum(axis=1)
    with np.errstate(divide="ignore"):
        inv_sqrt = np.where(degree > 0, 1.0 / np.sqrt(np.where(degree > 0, degree, 1.0)), 0.0)
    return (inv_sqrt[:, None] * adjacency.T * inv_sqrt[None, :]).astype(np.float32)
