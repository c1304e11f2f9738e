"""The episodes an evaluation runs: a split's fixed set or an episode file, checked against the
scenes' simulator settings and cut to the first episodes of each room type, and the digest that
names a set in caches and manifests."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from mapless.episodes import evalsets
from mapless.errors import MaplessError
from mapless.evaluate.runner import LibrarySpec
from mapless.scenes.catalogue import ROOM_TYPES, room_type_of
from mapless.sim.episode import Episode


def load_episodes(
    split: str,
    episodes_file: str | Path | None = None,
    per_room: int | None = None,
    rooms: Sequence[str] = ROOM_TYPES,
    library: LibrarySpec | None = None,
    target_set: str = "mjolnir22",
    layouts: str | None = None,
) -> list[Episode]:
    """The fixed episodes of ``split`` (:func:`mapless.episodes.evalsets.set_path`: ``episodes_file``,
    else the built-in set of the training ``target_set``, hoz22's reference sets the published ones;
    with ``layouts`` the layout-shift set, made on the spot when not shipped), keeping the first
    ``per_room`` of each room type in ``rooms``: a prefix of the full set, so small budgets evaluate a
    subset of the very episodes the full budget uses (the published sets are in their files' order,
    which is shuffled: HOZ evaluates the first 250 of each room type).

    With a built-in simulator ``library``, a file made under other simulator settings is refused: its
    shortest paths (SPL, the L>=5 split) and its "target not yet visible" starts would be wrong there.
    """
    path = evalsets.set_path(split, target_set, layouts, episodes_file)
    if layouts and not episodes_file and not path.exists() and library is not None:
        # A layout-shift set not shipped: made here, as `mapless episodes make --layouts` makes it (its
        # first per_room episodes of each room type are those of the full set: each room draws alone).
        made = evalsets.make_eval_set(
            library.build(), split, target_set, per_room or 250, layouts=layouts, room_types=tuple(rooms)
        )
        return first_per_room(made, per_room, rooms, source=f"the {split} set under layouts {layouts}")
    if not path.exists():
        raise MaplessError(
            f"no episode file {path}; make the fixed sets with "
            f"`mapless episodes make --target-set {target_set}` or pass --episodes FILE"
        )
    episodes, _ = evalsets.load(path, library.sim_fingerprint if library else None)
    return first_per_room(episodes, per_room, rooms, source=str(path))


def first_per_room(
    episodes: Sequence[Episode],
    per_room: int | None,
    rooms: Sequence[str] = ROOM_TYPES,
    source: str = "the set",
) -> list[Episode]:
    """The first ``per_room`` episodes of each room type in ``rooms`` (all with None), in order."""
    kept: list[Episode] = []
    count = dict.fromkeys(rooms, 0)
    for episode in episodes:
        room = room_type_of(episode.scene)
        if room in count and (per_room is None or count[room] < per_room):
            kept.append(episode)
            count[room] += 1
    if not kept:
        raise MaplessError(f"{source} has no episodes of room types {list(rooms)}")
    return kept


def episodes_digest(episodes: Sequence[Episode]) -> str:
    """Sixteen hex digits naming an episode set by its content, in order (caches, zoo manifests)."""
    text = json.dumps([e.to_dict() for e in episodes], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
