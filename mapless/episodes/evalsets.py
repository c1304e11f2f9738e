"""Fixed evaluation episode sets: deterministic from a seed, versioned, stored as JSON.

Per room type, ``per_room`` episodes: scene uniform over the split's scenes of the room, target
drawn over visible instances of the room's targets (as in training), start a uniform (position,
yaw) at horizon 0 from which the target is reachable, in the scene's usable pose-graph component
(``SceneData.usable_poses``; the ``standard`` and ``paper`` sets predate that rule, see
``Protocol.island_starts``). Under the ``standard`` and ``paper`` protocols the start must not already
see the target; the ``reference`` protocol's sets (``ref_val``, ``ref_test``) allow it, as the
references' published sets do. The optimal length (actions including ``Done``) is stored. The file
records the simulator fingerprint it was made with; loading it under other simulator parameters is
an error, since lengths would differ.
"""

from __future__ import annotations

import gzip
import io
import json
import zlib
from importlib import resources
from pathlib import Path

import numpy as np

from mapless.episodes.protocols import protocol_of_split
from mapless.errors import MaplessError
from mapless.files import write_bytes
from mapless.scenes.catalogue import ROOM_TYPES, scene_names, split_range_label
from mapless.scenes.categories import targets
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary

FORMAT = "mapless-episodes/1"
EVAL_SPLITS = ("val", "test", "paper", "ref_val", "ref_test")


def make_eval_set(
    library: SceneLibrary,
    split: str,
    target_set: str = "mjolnir22",
    per_room: int = 250,
    seed: int = 0,
    room_types: tuple[str, ...] = ROOM_TYPES,
) -> list[Episode]:
    room_targets = targets(target_set)
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
            if not (protocol.island_starts or data.usable_poses[start]):
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


def dumps(episodes: list[Episode], split: str, target_set: str, seed: int, sim_fingerprint: str) -> bytes:
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
    text = json.dumps(payload, sort_keys=True, indent=0).encode()
    buffer = io.BytesIO()
    with gzip.GzipFile(fileobj=buffer, mode="wb", mtime=0, compresslevel=9) as f:
        f.write(text)
    return buffer.getvalue()


def save(
    path: Path, episodes: list[Episode], split: str, target_set: str, seed: int, sim_fingerprint: str
) -> None:
    write_bytes(path, dumps(episodes, split, target_set, seed, sim_fingerprint))


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


def builtin_path(split: str, target_set: str = "mjolnir22") -> Path:
    if split not in EVAL_SPLITS:
        raise MaplessError(f"no built-in episode set for split {split!r}; choose one of {EVAL_SPLITS}")
    return Path(str(resources.files("mapless.data").joinpath(f"episodes/{split}_{target_set}.json.gz")))
