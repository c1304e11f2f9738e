"""Our episode sets as SAVN or MJOLNIR evaluation pickles, readable by the originals' code."""

from __future__ import annotations

import copyreg
import io
import pickle
from collections.abc import Callable, Collection, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mapless.errors import MaplessError
from mapless.files import write_bytes
from mapless.offline.episodes import TYPE_ALIASES
from mapless.offline.format import DEFAULT_AGENT_Y, check_format, scene_folder_name
from mapless.sim.episode import Episode

#: The room names MJOLNIR's pickles carry in their ``room`` field.
MJOLNIR_ROOM_NAMES = {
    "kitchen": "Kitchen",
    "living_room": "Living_Room",
    "bedroom": "Bedroom",
    "bathroom": "Bathroom",
}
#: Where the originals' start-state class lives; our pickles name it so their loader rebuilds it.
THOR_STATE_MODULE = "datasets.offline_controller_with_small_rotation"
THOR_STATE_CLASS = "ThorAgentState"


class _ThorAgentState:
    """Written under the originals' class path, so their ``pickle.load`` rebuilds a real
    ``ThorAgentState`` (plain attributes, no custom state handling)."""

    def __init__(self, x: float, y: float, z: float, rotation: int, horizon: int):
        self.x, self.y, self.z, self.rotation, self.horizon = x, y, z, rotation, horizon

    def __reduce_ex__(self, protocol: int) -> tuple:
        return copyreg.__newobj__, (type(self),), dict(self.__dict__)


class _EpisodePickler(pickle._Pickler):
    """Pure-Python pickler that names :class:`_ThorAgentState` by the originals' class path (the
    class is not importable there under our name, and we cannot import theirs)."""

    def save_global(self, obj: Any, name: str | None = None) -> None:
        if obj is _ThorAgentState:
            self.write(pickle.GLOBAL + f"{THOR_STATE_MODULE}\n{THOR_STATE_CLASS}\n".encode())
            self.memoize(obj)
            return
        super().save_global(obj, name)


#: The references' file name per mapless split: ``{room}_{suffix}.pkl`` (SAVN's ``test_val_split``).
ROOM_FILE_SUFFIX = {"val": "val", "test": "test", "paper": "test_val", "ref_val": "val", "ref_test": "test"}
#: The references evaluate the first ``--num_ep`` = 250 entries of each room's file.
REFERENCE_EPISODES_PER_ROOM = 250


def embedding_for(target: str, embeddings: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """``target``'s vector, else that of a v1 name standing for it (SAVN's GloVe table has ``Lamp``
    but no ``DeskLamp``, ``CoffeeMaker`` but no ``CoffeeMachine``)."""
    if target in embeddings:
        return embeddings[target]
    return next(
        (embeddings[v1] for v1, v5 in TYPE_ALIASES.items() if target in v5 and v1 in embeddings), None
    )


def write_episode_file(
    episodes: Iterable[Episode],
    path: str | Path,
    format: str = "savn",
    *,
    embeddings: Mapping[str, np.ndarray],
    agent_y: float = DEFAULT_AGENT_Y,
    visible_ids: Callable[[str], Collection[str]] | None = None,
) -> int:
    """Write ``episodes`` as a SAVN or MJOLNIR evaluation pickle; returns the number written.

    Each entry has ``scene`` (SAVN spelling: ``FloorPlan1_physics`` for kitchens and living rooms),
    ``goal_object_type``, ``task_data`` (the episode's ``target_ids``, or else every instance of the
    target type in the built-in scene, as SAVN's own sampler does), ``state`` (a
    ``ThorAgentState``) and ``glove_embedding`` (a torch FloatTensor for SAVN, a float32 array for
    MJOLNIR, which also gets ``room``). ``embeddings`` maps each target type (or its v1 name) to its
    vector.

    ``visible_ids(scene)``: the ids of the scene's visible-object map (``mapless export``'s
    ``visible_object_map.json``). ``task_data`` then lists only those: MJOLNIR's ``Done`` looks every
    id up in that map and raises ``KeyError`` on one no pose sees. An episode left with none is an
    error (its target can never be seen; our sets never hold one).
    """
    from mapless.scenes import load_scene, room_type_of

    check_format(format)
    entries = []
    for episode in episodes:
        embedding = embedding_for(episode.target, embeddings)
        if embedding is None:
            raise MaplessError(
                f"no embedding for target type {episode.target!r} (episode {episode.episode_id or '?'} "
                f"of {episode.scene}); the embedding table has {len(embeddings)} types"
            )
        vector = np.asarray(embedding, dtype=np.float32).reshape(-1)
        task = list(episode.target_ids)
        if not task:
            scene = load_scene(episode.scene)
            task = [scene.objects[i].id for i in scene.instances_of(episode.target)]
        if visible_ids is not None:
            seen = visible_ids(episode.scene)
            task = [i for i in task if i in seen]
            if not task:
                raise MaplessError(
                    f"episode {episode.episode_id or '?'} of {episode.scene}: no pose sees any "
                    f"{episode.target}, so no target id is in the scene's visible-object map"
                )
        x, z, yaw, horizon = episode.start
        entry: dict[str, Any] = {
            "scene": scene_folder_name(episode.scene, format),
            "goal_object_type": episode.target,
            "task_data": task,
            "state": _ThorAgentState(round(float(x), 2), agent_y, round(float(z), 2), int(yaw), int(horizon)),
        }
        if format == "savn":
            import torch

            entry["glove_embedding"] = torch.from_numpy(vector.copy())
        else:
            entry["glove_embedding"] = vector
            entry["room"] = MJOLNIR_ROOM_NAMES.get(room_type_of(episode.scene), "")
        entries.append(entry)
    buffer = io.BytesIO()
    # Protocol 2: readable by the Python 3.6 / PyTorch 0.4 environment of the originals.
    _EpisodePickler(buffer, protocol=2).dump(entries)
    write_bytes(path, buffer.getvalue())
    return len(entries)


def write_room_files(
    episodes: Iterable[Episode], folder: str | Path, split: str, format: str = "savn", **kwargs: Any
) -> dict[str, Path]:
    """One pickle per room type, ``<folder>/<room>_<suffix>.pkl`` (``ROOM_FILE_SUFFIX``; ``test`` for
    our test sets, ``test_val`` for x21-x30), the layout the references read with
    ``--test_or_val``; ``kwargs`` go to :func:`write_episode_file`. Returns the files by room type."""
    from mapless.scenes import room_type_of
    from mapless.scenes.catalogue import ROOM_TYPES

    by_room: dict[str, list[Episode]] = {}
    for episode in episodes:
        by_room.setdefault(room_type_of(episode.scene), []).append(episode)
    suffix = ROOM_FILE_SUFFIX.get(split, split)
    paths = {}
    for room in (r for r in ROOM_TYPES if r in by_room):
        paths[room] = Path(folder) / f"{room}_{suffix}.pkl"
        write_episode_file(by_room[room], paths[room], format, **kwargs)
    return paths
