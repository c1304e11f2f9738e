"""Parent objects per room type (the paper's hierarchical semantic information) and the parent reward.

A *parent* of a target is a larger object (a category never pickupable in the training scenes) that is
semantically or spatially related to the target in a room type, e.g. ``Drawer`` for ``Television`` in
living rooms. The lists are built by :func:`build_parent_lists` from two sources, training scenes only:

1. MJOLNIR's ``c2p_top3.json`` (top-3 parents of its 22 targets), kept where the training scenes of
   that room support the relation at least once;
2. receptacle statistics of the 80 training floor plans (``FloorPlan{x01..x20}``): every category that
   holds at least :data:`RECEPTACLE_SHARE` of the target's instances, then, while a list has fewer than
   :data:`MIN_PARENTS` entries, the categories found within :data:`NEAR_DISTANCE` m (xz) of at least
   :data:`NEAR_SHARE` of the instances.

Each parent carries ``p``: the share of the target's training instances that lie on/in the parent or
within ``NEAR_DISTANCE`` of one of its instances. ``p`` plays the role of MJOLNIR's child->parent
probability in the reward. The built lists ship as ``mapless/data/priors/parents.json`` (a test checks
they equal a rebuild) and are tabulated in docs/guide/models.md.
"""

from __future__ import annotations

import functools
import json
from collections import Counter
from collections.abc import Iterable, Mapping
from importlib import resources

import numpy as np

from mapless.errors import UnknownNameError
from mapless.scenes.catalogue import ROOM_TYPES, scene_names
from mapless.scenes.categories import CATEGORY_SETS, TARGET_SETS, V1_TO_V5, category_set

PARENTS_FILE = "priors/parents.json"
C2P_FILE = "priors/c2p_top3.json"
C2P_ROOMS = {"Kitchen": "kitchen", "Living_Room": "living_room", "Bedroom": "bedroom", "Bathroom": "bathroom"}
#: A receptacle category becomes a parent when it holds at least this share of the target's instances.
RECEPTACLE_SHARE = 0.25
#: Lists shorter than this are filled with nearby categories (wall-mounted targets have no receptacle).
MIN_PARENTS = 3
NEAR_DISTANCE = 1.0
NEAR_SHARE = 0.5


def _category_of(type_name: str, set_name: str) -> str | None:
    cats = category_set(set_name)
    index = cats.type_to_index.get(type_name)
    return None if index is None else cats.names[index]


def _c2p_parents(set_name: str) -> dict[str, dict[str, list[str]]]:
    """c2p_top3 parents per (room, target) in the set's category names (v1 names mapped onto v5)."""
    raw = json.loads(resources.files("mapless.data").joinpath(C2P_FILE).read_text())
    out: dict[str, dict[str, list[str]]] = {}
    for room_key, per_target in raw.items():
        room = C2P_ROOMS[room_key]
        for target, parents in per_target.items():
            names: list[str] = []
            for parent in parents:
                # TableTop means DiningTable or CoffeeTable in v5; both are checked against the data.
                for v5 in V1_TO_V5.get(parent, (parent,)):
                    cat = _category_of(v5, set_name)
                    if cat is not None and cat not in names:
                        names.append(cat)
            out.setdefault(room, {})[target] = names
    return out


def _relation_statistics(room: str, target: str, set_name: str) -> tuple[int, Counter, Counter, set[str]]:
    """(#target instances, on-counts, on-or-near counts, movable categories) over training scenes."""
    from mapless.scenes.layout import load_scene

    n, on, related, pickupable = 0, Counter(), Counter(), set()
    for name in scene_names("train", (room,)):
        scene = load_scene(name)
        cats = [_category_of(o.type, set_name) for o in scene.objects]
        pickupable.update(c for c, o in zip(cats, scene.objects, strict=True) if c and o.pickupable)
        xz = np.array([(o.center[0], o.center[2]) for o in scene.objects])
        for i, obj in enumerate(scene.objects):
            if obj.type != target and cats[i] != target:
                continue
            n += 1
            on_cats = {
                _category_of(scene.object(p).type, set_name) for p in obj.parents if p in scene.object_index
            }
            near = np.hypot(*(xz - xz[i]).T) < NEAR_DISTANCE
            near_cats = {cats[j] for j in np.flatnonzero(near)}
            on.update(c for c in on_cats if c)
            related.update(c for c in on_cats | near_cats if c)
    return n, on, related, pickupable


def _entry(entries: dict[str, dict], cat: str, n: int, on: Counter, related: Counter) -> dict:
    return entries.setdefault(
        cat, {"parent": cat, "p": round(related[cat] / n, 3), "on": round(on[cat] / n, 3), "sources": []}
    )


def _by_count(counts: Counter) -> list[tuple[str, int]]:
    """Most common first, ties by name (Counter's tie order follows set iteration, i.e. string hashing)."""
    return sorted(counts.items(), key=lambda item: (-item[1], item[0]))


def build_parent_lists(set_name: str = "mjolnir101") -> dict[str, dict[str, list[dict]]]:
    """Parent lists ``{room: {target: [{parent, p, on, sources}]}}`` for every target of every target set."""
    c2p = _c2p_parents(set_name)
    lists: dict[str, dict[str, list[dict]]] = {}
    for room in ROOM_TYPES:
        room_targets = dict.fromkeys(t for ts in TARGET_SETS.values() for t in ts[room])
        for target in room_targets:
            n, on, related, pickupable = _relation_statistics(room, target, set_name)
            target_cat = _category_of(target, set_name)
            entries: dict[str, dict] = {}
            excluded = pickupable | {target_cat, "Floor"}  # parents are larger objects, not the target
            candidates = [
                (cat, "c2p_top3") for cat in c2p.get(room, {}).get(target, []) if n and related[cat] > 0
            ]
            candidates += [
                (cat, "receptacle") for cat, count in _by_count(on) if count / n >= RECEPTACLE_SHARE
            ]
            for cat, source in candidates:
                if cat not in excluded:
                    _entry(entries, cat, n, on, related)["sources"].append(source)
            for cat, count in _by_count(related):
                if len(entries) >= MIN_PARENTS or count / n < NEAR_SHARE:
                    break
                if cat not in excluded and cat not in entries:
                    _entry(entries, cat, n, on, related)["sources"].append("near")
            ordered = sorted(entries.values(), key=lambda e: (-e["p"], e["parent"]))
            lists.setdefault(room, {})[target] = ordered
    return lists


@functools.cache
def parent_lists(set_name: str = "mjolnir101") -> dict[str, dict[str, list[dict]]]:
    """The shipped parent lists of a category set (see :func:`build_parent_lists`)."""
    if set_name not in CATEGORY_SETS:
        raise UnknownNameError("category set", set_name, CATEGORY_SETS)
    return json.loads(resources.files("mapless.data").joinpath(PARENTS_FILE).read_text())[set_name]


def parents_of(room_type: str, target: str, set_name: str = "mjolnir101") -> dict[str, float]:
    """``{parent category: p}`` of a target in a room type (empty when the target has none there)."""
    lists = parent_lists(set_name)
    if room_type not in lists:
        raise UnknownNameError("room type", room_type, lists)
    return {e["parent"]: e["p"] for e in lists[room_type].get(target, [])}


def parent_weights(room_type: str, target: str, set_name: str = "mjolnir101") -> np.ndarray:
    """``[C]`` float32: ``p`` at each parent's category row, 0 elsewhere (input of :func:`parent_reward`)."""
    cats = category_set(set_name)
    weights = np.zeros(len(cats), dtype=np.float32)
    for parent, p in parents_of(room_type, target, set_name).items():
        weights[cats.index(parent)] = p
    return weights


def parent_reward(
    in_view: np.ndarray, weights: np.ndarray, seen: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """MJOLNIR's hierarchical-relationship bonus, per episode and vectorised over episodes.

    ``in_view`` (bool ``[..., C]``): categories in view at this step (MJOLNIR used the success rule's
    visibility); ``weights`` (``[..., C]``, :func:`parent_weights`); ``seen`` (bool ``[..., C]``):
    parents already rewarded *in this episode* (all False at reset; MJOLNIR leaked it across episodes).
    Returns ``(bonus [...], new_seen)``: the largest ``p`` among parents in view and not yet seen (0 if
    none), and ``seen`` with that one parent added (as MJOLNIR appends only the rewarded object, another
    parent in view can pay on a later step). The environment uses the bonus *instead of* the step
    penalty when it is positive, and never adds it to the success reward. Inputs are not modified.
    """
    in_view, weights, seen = (
        np.asarray(in_view, bool),
        np.asarray(weights, np.float32),
        np.asarray(seen, bool),
    )
    candidates = np.where(in_view & ~seen & (weights > 0), weights, 0.0)
    best = np.argmax(candidates, axis=-1)
    bonus = np.take_along_axis(candidates, best[..., None], axis=-1)[..., 0]
    new_seen = seen.copy()
    rewarded = bonus > 0
    np.put_along_axis(
        new_seen, best[..., None], np.take_along_axis(new_seen, best[..., None], -1) | rewarded[..., None], -1
    )
    return bonus.astype(np.float32), new_seen


def parent_reward_by_name(
    in_view: Iterable[str], parents: Mapping[str, float], seen: set[str]
) -> tuple[float, set[str]]:
    """Name-based :func:`parent_reward` for a single episode: ``(bonus, new seen set)``."""
    candidates = {c: parents[c] for c in set(in_view) if c in parents and c not in seen and parents[c] > 0}
    if not candidates:
        return 0.0, set(seen)
    best = max(sorted(candidates), key=candidates.__getitem__)
    return float(candidates[best]), set(seen) | {best}
