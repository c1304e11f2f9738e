"""Fixed evaluation episode sets: deterministic from a seed, versioned, stored as JSON.

Per room type, ``per_room`` episodes: scene uniform over the split's scenes of the room, target
drawn over visible instances of the room's targets (as in training), start a uniform (position,
yaw) at horizon 0 from which the target is reachable, in the scene's usable pose-graph component
(``SceneData.usable_poses``). Under the ``standard`` and ``paper`` protocols the start must not already
see the target; the ``reference`` protocol's sampled sets (``ref_val``, ``ref_test``) allow it, as the
references' published sets do. A target set that is a published set (:data:`PUBLISHED`: ``hoz22``)
has its published episodes as its reference sets instead: the shipped files mapped onto the built-in
scenes (:func:`map_published`), stored like the sampled sets under its name. An evaluation reads the
sets of the model's training target set (:func:`set_path`), so that it is scored on the targets it
was trained for; :func:`untrained_targets` finds the episodes of any other episode file that are not.
The optimal length (actions including ``Done``) is stored. The file records the simulator
fingerprint it was made with; loading it under other simulator parameters is an error, since lengths
would differ.

Layout-shift sets (``layouts="gen:3"``: SOURCE:PER_SCENE) play the split's floor plans under other
arrangements: after the floor plan, one more draw picks one of its first PER_SCENE variants from
SOURCE (mapless.scenes.variants.variants_of), uniformly; the rest is as above, on the variant. The
file records ``layouts``; the built-in ``test`` set under ``gen:3`` is ``test_gen3_<targets>``.
"""

from __future__ import annotations

import gzip
import io
import json
import zlib
from collections.abc import Iterable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapless.episodes.protocols import protocol_of_split
from mapless.errors import MaplessError
from mapless.files import write_bytes
from mapless.scenes.catalogue import ROOM_TYPES, room_type_of, scene_names, split_range_label
from mapless.scenes.categories import targets
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary

if TYPE_CHECKING:
    from mapless.offline.episodes import MappingReport

FORMAT = "mapless-episodes/1"
EVAL_SPLITS = ("val", "test", "paper", "ref_val", "ref_test")
#: Published episode files the package ships (mapless/data/NOTICE.md), by set name: the file of a
#: room type and split, and which of our splits each of their splits is. ``hoz22``: the HOZ line's
#: 22-class val (odd x21-x29) and test (even x22-x30) files, the reference protocol's sets of the
#: target set ``hoz22`` (mapless.scenes.categories.HOZ22_TARGETS, their classes).
PUBLISHED: dict[str, tuple[str, dict[str, str]]] = {
    "hoz22": ("episodes/hoz22/{room}_{split}_22.pkl.gz", {"ref_val": "val", "ref_test": "test"}),
}


def make_eval_set(
    library: SceneLibrary,
    split: str,
    target_set: str = "mjolnir22",
    per_room: int = 250,
    seed: int = 0,
    room_types: tuple[str, ...] = ROOM_TYPES,
    layouts: str | None = None,
) -> list[Episode]:
    if is_published(split, target_set):  # mapped, not sampled: per_room and seed do not apply
        if layouts:
            raise MaplessError(f"the published set {target_set} has no layout-shift version")
        return map_published(library, split, target_set, room_types)[0]
    room_targets = targets(target_set)
    source, per_scene = parse_layouts(layouts) if layouts else (None, 0)
    protocol = protocol_of_split(split)
    # A start that already sees the target has distance 0: allowed only where the protocol says so.
    nearest = 0 if protocol.visible_starts else 1
    episodes = []
    for room in room_types:
        rng = np.random.default_rng([seed, ROOM_TYPES.index(room)])
        scenes = scene_names(split, (room,))
        made = 0
        attempts = 0
        while made < per_room:
            attempts += 1
            if attempts > 200 * per_room:
                raise MaplessError(f"could not make {per_room} valid {room} episodes for split {split}")
            scene = scenes[rng.integers(len(scenes))]
            if source is not None:
                variants = _variants(scene, source, per_scene)
                scene = variants[rng.integers(len(variants))]
            data = library[scene]
            _, visible = data.visible_matrix_csr
            types = [data.instance_types[i] for i in np.unique(visible)]
            types = [t for t in types if t in room_targets[room]]
            starts = np.flatnonzero(data.horizon == 0)
            if not types:
                continue
            target = types[rng.integers(len(types))]
            start = int(starts[rng.integers(len(starts))])
            distance = int(data.target_distances(target)[start])
            if distance < nearest:  # unreachable (-1), or in view (0) where the protocol refuses that
                continue
            if not data.usable_poses[start]:
                continue
            episodes.append(
                Episode(
                    scene=scene,
                    target=target,
                    start=data.pose_tuple(start),
                    optimal_length=distance + 1,
                    episode_id=f"{split}/{room}/{made:03d}",
                )
            )
            made += 1
    return episodes


def map_published(
    library: SceneLibrary, split: str, name: str = "hoz22", room_types: tuple[str, ...] = ROOM_TYPES
) -> tuple[list[Episode], dict[str, MappingReport]]:
    """The shipped published episodes of ``split`` mapped onto ``library``'s scenes, room type by
    room type in file order (``episode_id`` ``<name>_<their split>/<room>/<index in the file>``),
    and each file's mapping report."""
    from mapless.offline.episodes import import_episode_file

    splits = PUBLISHED[name][1]
    episodes: list[Episode] = []
    reports: dict[str, MappingReport] = {}
    for room in room_types:
        path = published_path(name, split, room)
        report = import_episode_file(
            path, scene_data=library.__getitem__, id_prefix=f"{name}_{splits[split]}"
        )
        episodes += report.episodes
        reports[path.name.removesuffix(".gz")] = report
    return episodes, reports


def is_published(split: str, target_set: str) -> bool:
    """Whether the ``split`` set of ``target_set`` is a published set's, mapped rather than sampled
    (``hoz22``'s ``ref_val`` and ``ref_test``; its other splits are sampled over its targets)."""
    return target_set in PUBLISHED and split in PUBLISHED[target_set][1]


def published_path(name: str, split: str, room: str) -> Path:
    """The shipped file of a published set's ``split`` (ours: ``ref_val``, ``ref_test``) and room type."""
    template, splits = PUBLISHED[name]
    if split not in splits:
        raise MaplessError(f"the published set {name} has no {split} episodes; it has {list(splits)}")
    return _data_path(template.format(room=room, split=splits[split]))


def parse_layouts(layouts: str) -> tuple[str, int]:
    """``"gen:3"`` -> ``("gen", 3)``: an arrangement source and how many variants per floor plan."""
    source, _, count = layouts.rpartition(":")
    if not source or not count.isdigit() or int(count) < 1:
        raise MaplessError(f"layouts {layouts!r}: expected SOURCE:PER_SCENE, e.g. gen:3 or rearrange2023:5")
    return source, int(count)


def _variants(scene: str, source: str, per_scene: int) -> list[str]:
    from mapless.scenes.variants import variants_of

    names = variants_of(scene, source, per_scene)
    if not names:
        raise MaplessError(f"arrangement source {source!r} has no usable arrangement of {scene}")
    return names


def layouts_label(layouts: str) -> str:
    """File-name label of a layout-shift set: ``gen:3`` -> ``gen3``, ``/x/val.pkl.gz:5`` -> ``val5``."""
    source, count = parse_layouts(layouts)
    stem = Path(source).name.split(".")[0] if source not in ("gen", "rearrange2023") else source
    return "".join(c for c in stem if c.isalnum() or c in "-_") + str(count)


def dumps(
    episodes: list[Episode],
    split: str,
    target_set: str,
    seed: int,
    sim_fingerprint: str,
    layouts: str | None = None,
) -> bytes:
    """Canonical bytes (sorted keys, gzip without timestamp) so regeneration is bit-for-bit."""
    payload = {
        "format": FORMAT,
        "split": split,
        "scenes": split_range_label(split),
        "target_set": target_set,
        "seed": seed,
        "sim_fingerprint": sim_fingerprint,
        "episodes": [e.to_dict() for e in episodes],
    }
    if layouts:  # only then: the default sets' bytes stay what they were
        payload["layouts"] = layouts
    text = json.dumps(payload, sort_keys=True, indent=0).encode()
    buffer = io.BytesIO()
    with gzip.GzipFile(fileobj=buffer, mode="wb", mtime=0, compresslevel=9) as f:
        f.write(text)
    return buffer.getvalue()


def save(path: Path, *args: Any, **kwargs: Any) -> None:
    """Write :func:`dumps` of the same arguments atomically to ``path``."""
    write_bytes(path, dumps(*args, **kwargs))


def load(path: Path | str, expected_fingerprint: str | None = None) -> tuple[list[Episode], dict]:
    """Episodes and header of an episode file; checks the format and, if given, the simulator."""
    path = Path(path)
    try:
        payload = json.loads(gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_text())
    except (OSError, ValueError, EOFError, zlib.error, RecursionError) as error:  # a torn .gz, deep nesting
        raise MaplessError(f"cannot read episode file {path}: {error}") from error
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else f"a JSON {type(payload).__name__}"
        raise MaplessError(f"{path}: not a {FORMAT} file (format {found!r})")
    for key, kind in (("episodes", list), ("sim_fingerprint", str), ("split", str), ("scenes", str)):
        if not isinstance(payload.get(key), kind):
            raise MaplessError(f"{path}: {key!r} is missing or not a {kind.__name__}")
    episodes = []
    for i, entry in enumerate(payload["episodes"]):
        try:
            episodes.append(Episode.from_dict(entry))
        except ValueError as error:
            raise MaplessError(f"{path}: episode {i}: {error}") from None
    if expected_fingerprint and payload["sim_fingerprint"] != expected_fingerprint:
        raise MaplessError(
            f"{path} was made with simulator {payload['sim_fingerprint']}, but the current simulator is "
            f"{expected_fingerprint}; regenerate it with `mapless episodes make`"
        )
    header = {k: v for k, v in payload.items() if k != "episodes"}
    return episodes, header


def set_path(
    split: str,
    target_set: str = "mjolnir22",
    layouts: str | None = None,
    episodes_file: str | Path | None = None,
) -> Path:
    """The episode file an evaluation of ``split`` reads: ``episodes_file`` (a path, or the name of
    a shipped set, e.g. ``ref_test_hoz22``, the published HOZ test episodes); else the shipped set
    of the model's ``target_set`` (with ``layouts``, its layout-shift set). The training target set
    decides, under every protocol: the reference protocol scores ``mjolnir22`` on its sampled
    ``ref_*_mjolnir22`` sets and ``hoz22`` on the published HOZ episodes (``ref_*_hoz22``)."""
    if episodes_file is not None:
        path = Path(episodes_file)
        shipped = _data_path(f"episodes/{path.name}.json.gz")
        named = not path.exists() and str(episodes_file) == path.name and shipped.is_file()
        return shipped if named else path
    return builtin_path(split, target_set, layouts)


def untrained_targets(episodes: Iterable[Episode], target_set: str) -> dict[str, dict[str, int]]:
    """``{room type: {target: episodes}}`` of the episodes whose target is not one of ``target_set``'s
    targets of their room type: targets a run trained on that set never navigated to there (the
    training sampler draws each room type's targets only). Empty when every episode is a training one."""
    room_targets = targets(target_set)
    found: dict[str, dict[str, int]] = {}
    for episode in episodes:
        room = room_type_of(episode.scene)
        if episode.target not in room_targets[room]:
            per_room = found.setdefault(room, {})
            per_room[episode.target] = per_room.get(episode.target, 0) + 1
    return found


def describe_untrained(found: dict[str, dict[str, int]], total: int, target_set: str) -> str:
    """One line on :func:`untrained_targets`' result: how many episodes, which classes per room type."""
    count = sum(n for per_room in found.values() for n in per_room.values())
    classes = "; ".join(
        f"{room}: " + ", ".join(f"{t} {n}" for t, n in sorted(per_room.items()))
        for room, per_room in found.items()
    )
    return (
        f"{count} of {total} episodes have targets the run never trained for (not among target set "
        f"{target_set}'s targets of their room type): {classes}"
    )


def _data_path(name: str) -> Path:
    return Path(str(resources.files("mapless.data").joinpath(name)))


def source_path(source: str, target_set: str = "mjolnir22") -> Path:
    """What a command's episode source names: an episode file, else the built-in set of a split
    (of ``target_set``); an error naming both readings when it is neither."""
    path = Path(source)
    if path.exists():
        return path
    if source not in EVAL_SPLITS:
        raise MaplessError(f"{source!r} is neither an episode file nor one of {EVAL_SPLITS}")
    return builtin_path(source, target_set)


def builtin_path(split: str, target_set: str = "mjolnir22", layouts: str | None = None) -> Path:
    """The shipped evaluation set of ``split`` (and of ``layouts``' arrangements) of ``target_set``."""
    if split not in EVAL_SPLITS:
        raise MaplessError(f"no built-in episode set for split {split!r}; choose one of {EVAL_SPLITS}")
    name = f"{split}_{layouts_label(layouts)}" if layouts else split
    return _data_path(f"episodes/{name}_{target_set}.json.gz")
