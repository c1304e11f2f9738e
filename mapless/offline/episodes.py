"""Published evaluation episode pickles (SAVN, MJOLNIR, HOZ): read, map onto the built-in scenes,
and write ours in the same format.

Reading needs none of the original classes: SAVN pickles hold a
``datasets.offline_controller_with_small_rotation.ThorAgentState`` start state and torch GloVe
tensors. The unpickler resolves only a fixed set of harmless globals (containers, numpy arrays,
torch tensors rebuilt with ``weights_only`` loading); every other global becomes an inert
placeholder that just records its constructor arguments and state, so an episode file can never
run code.

Mapping: AI2-THOR object ids changed between versions, so a target id is matched verbatim when
the built-in scene has it, else to the nearest object of the same type (v1 names translated) by
horizontal distance. Start poses snap to the nearest built-in pose with the same yaw and horizon.
Episodes that cannot be mapped are listed with the reason and skipped.
"""

from __future__ import annotations

import collections
import copyreg
import io
import math
import pickle
import re
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapless.errors import MaplessError
from mapless.files import write_bytes
from mapless.offline.format import (
    DEFAULT_AGENT_Y,
    OfflineFormatError,
    check_format,
    object_type_of_id,
    parse_pose_key,
    scene_folder_name,
)
from mapless.sim.episode import Episode
from mapless.sim.scene_data import SceneData, pose_key

#: v1/SAVN type names -> AI2-THOR 5 types whose instances stand for them when mapping targets.
TYPE_ALIASES: dict[str, tuple[str, ...]] = {
    "CoffeeMaker": ("CoffeeMachine",),
    "Lamp": ("DeskLamp", "FloorLamp"),
    "TableTop": ("DiningTable", "CoffeeTable"),
    "NightStand": ("SideTable",),
    "Glassbottle": ("Bottle",),
    "ToiletPaperRoll": ("ToiletPaper",),
}
MJOLNIR_ROOM_NAMES = {
    "kitchen": "Kitchen",
    "living_room": "Living_Room",
    "bedroom": "Bedroom",
    "bathroom": "Bathroom",
}
THOR_STATE_MODULE = "datasets.offline_controller_with_small_rotation"
THOR_STATE_CLASS = "ThorAgentState"
DEFAULT_MAX_TARGET_DISTANCE = 0.5  # m, horizontal; 96 % of HOZ targets lie within 0.3 m
DEFAULT_MAX_START_DISTANCE = 0.36  # m: one diagonal grid step


# ---------------------------------------------------------------------------------------- reading


class Placeholder:
    """Stand-in for a class that is not importable here (``ThorAgentState``...)."""

    pickled_module = ""
    pickled_name = ""

    def __init__(self, *args: Any, **kwargs: Any):
        self.args = args
        self.__dict__.update(kwargs)

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict, slots) of __slots__ classes
            for part in state:
                if isinstance(part, dict):
                    self.__dict__.update(part)
        elif isinstance(state, dict):
            self.__dict__.update(state)
        else:
            self.state = state

    def __call__(self, *args: Any, **kwargs: Any) -> Placeholder:
        # A REDUCE through a placeholder "function" (getattr(obj, name)(...)) stays inert too.
        return Placeholder(*args, **kwargs)

    def __repr__(self) -> str:
        # Names only: the values come from the file and may be shared or nested without bound.
        fields = [k if isinstance(k, str) else type(k).__name__ for k in self.__dict__ if k != "args"]
        return f"<{self.pickled_module}.{self.pickled_name} with {', '.join(fields[:8]) or 'no fields'}>"


def _safe_load_from_bytes(data: bytes) -> Any:
    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


#: dtype names a pickled array may have: booleans and plain numbers of the usual widths.
_NUMERIC_DTYPE = re.compile(r"[biufc]\d{1,2}")


class _PickledDtype:
    """``numpy.dtype(name, align, copy)`` of a pickle, checked when its state arrives: only plain
    numeric types (kinds b, i, u, f, c; no fields, no sub-arrays) become a dtype."""

    def __init__(self, name: Any = "", align: Any = False, copy: Any = False):
        self.name = name
        self.dtype: np.dtype | None = None

    def __setstate__(self, state: Any) -> None:
        order = state[1] if isinstance(state, tuple) and len(state) > 1 else "|"
        subarray = state[2] if isinstance(state, tuple) and len(state) > 2 else None
        fields = state[3:5] if isinstance(state, tuple) and len(state) > 4 else (None, None)
        if not (isinstance(self.name, str) and _NUMERIC_DTYPE.fullmatch(self.name)):
            raise pickle.UnpicklingError(f"array dtype {self.name!r} is not a plain numeric type")
        if subarray is not None or any(f is not None for f in fields) or order not in ("<", ">", "|", "="):
            raise pickle.UnpicklingError(
                f"array dtype {self.name!r} has fields, sub-arrays or a bad byte order"
            )
        self.dtype = np.dtype(self.name).newbyteorder(order if order != "|" else "=")

    def resolve(self) -> np.dtype:
        if self.dtype is None:
            self.__setstate__(())
        return self.dtype


def _dtype_of(value: Any) -> np.dtype:
    if not isinstance(value, _PickledDtype):
        raise pickle.UnpicklingError(f"array dtype given as {type(value).__name__}")
    return value.resolve()


class _PickledArray:
    """A numpy array of a pickle (``_reconstruct`` then its state), rebuilt by :meth:`array` from a
    checked shape, dtype and the exact number of bytes; anything else is an UnpicklingError."""

    def __init__(self, *args: Any):
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def array(self) -> np.ndarray:
        state = self.state
        if not (isinstance(state, tuple) and len(state) == 5):
            raise pickle.UnpicklingError("array state is not (version, shape, dtype, fortran, data)")
        _, shape, dtype, fortran, data = state
        dtype = _dtype_of(dtype)
        if not (isinstance(shape, tuple) and all(isinstance(n, int) and 0 <= n < 2**31 for n in shape)):
            raise pickle.UnpicklingError(f"array shape {shape!r} is not a tuple of sizes")
        if not isinstance(data, bytes | bytearray):
            raise pickle.UnpicklingError("array data is not raw bytes (object arrays are refused)")
        count = int(np.prod(shape, dtype=np.int64))
        if len(data) != count * dtype.itemsize:
            raise pickle.UnpicklingError(f"array of shape {shape} and dtype {dtype} with {len(data)} bytes")
        flat = np.frombuffer(bytes(data), dtype=dtype, count=count)
        return flat.reshape(shape, order="F" if fortran else "C").copy()


def _pickled_scalar(dtype: Any, data: Any = b"") -> Any:
    dtype = _dtype_of(dtype)
    if not isinstance(data, bytes) or len(data) != dtype.itemsize:
        raise pickle.UnpicklingError(f"numpy scalar of dtype {dtype} with {len(data)} bytes")
    return np.frombuffer(data, dtype=dtype, count=1)[0]


def _materialize(value: Any, depth: int = 0, done: dict[int, Any] | None = None) -> Any:
    """The unpickled structure with every :class:`_PickledArray` rebuilt as an ndarray.

    Each object is visited once (``done``, by id): a pickle can share one list between many
    parents, level after level, and a walk that revisited shared objects would take 2**depth steps.
    A cycle is refused by the depth limit."""
    done = {} if done is None else done
    if depth > 50:
        raise pickle.UnpicklingError("episode data nested deeper than 50 levels (or a cycle)")
    if id(value) in done:
        return done[id(value)]
    result = value
    if isinstance(value, _PickledArray):
        result = value.array()
    elif isinstance(value, _PickledDtype):
        result = value.resolve()
    elif isinstance(value, list):
        result = [_materialize(v, depth + 1, done) for v in value]
    elif isinstance(value, tuple):
        result = tuple(_materialize(v, depth + 1, done) for v in value)
    elif isinstance(value, dict):
        result = {k: _materialize(v, depth + 1, done) for k, v in value.items()}
    elif isinstance(value, Placeholder):
        value.__dict__.update({k: _materialize(v, depth + 1, done) for k, v in value.__dict__.items()})
    done[id(value)] = result
    return result


def _no_size(kind: type) -> Callable[..., Any]:
    """``bytes``/``bytearray`` for a pickle: built from data in the file, never from a size (a
    ``bytes(10**10)`` in a few bytes of pickle would allocate gigabytes)."""

    def build(*args: Any) -> Any:
        if args and isinstance(args[0], int):
            raise pickle.UnpicklingError(f"{kind.__name__} of a size ({args[0]}) in an episode file")
        return kind(*args)

    return build


def _reconstructor(cls: Any, base: Any, state: Any) -> Any:
    """``copyreg._reconstructor`` of protocol 0/1 pickles, for placeholder classes on ``object``
    or a plain container only: other classes and bases (``bytes`` of a size) are refused."""
    if not (isinstance(cls, type) and issubclass(cls, base) and base in _RECONSTRUCTOR_BASES):
        raise pickle.UnpicklingError(f"copyreg._reconstructor of {cls!r} on {base!r}")
    return copyreg._reconstructor(cls, base, state)


_RECONSTRUCTOR_BASES = (object, list, dict, tuple, set, frozenset, int, float, str)


def _check_opcodes(data: bytes) -> None:
    """Walk the pickle's opcodes before the C unpickler runs: a length that runs past the end of the
    data, or a memo index beyond the objects stored so far, is refused here, because the unpickler
    would first allocate what it claims (gigabytes from a few bytes of a damaged file)."""
    import pickletools

    stored = 0
    try:
        for opcode, arg, _ in pickletools.genops(data):
            if opcode.name == "MEMOIZE":
                stored += 1
            elif opcode.name in ("PUT", "BINPUT", "LONG_BINPUT"):
                if not (isinstance(arg, int) and 0 <= arg <= stored):
                    raise pickle.UnpicklingError(f"memo index {arg!r} out of order")
                stored = max(stored, arg + 1)
            elif opcode.name in ("GET", "BINGET", "LONG_BINGET") and not (
                isinstance(arg, int) and 0 <= arg < stored
            ):
                raise pickle.UnpicklingError(f"memo index {arg!r} was never stored")
    except ValueError as error:  # pickletools' own complaints (truncated data, bad opcodes, ...)
        raise pickle.UnpicklingError(str(error)) from None


def _safe_globals() -> dict[tuple[str, str], Any]:
    import builtins

    allowed: dict[tuple[str, str], Any] = {}
    for name in (
        "list",
        "dict",
        "set",
        "frozenset",
        "tuple",
        "int",
        "float",
        "complex",
        "str",
        "bool",
        "slice",
        "object",
    ):
        # "__builtin__" is how Python 2 pickles (protocol <= 2) name the same module.
        allowed[("builtins", name)] = allowed[("__builtin__", name)] = getattr(builtins, name)
    for name in ("bytes", "bytearray"):
        allowed[("builtins", name)] = allowed[("__builtin__", name)] = _no_size(getattr(builtins, name))
    # range is left out: list(range(10**12)) would be a few bytes of pickle.
    allowed[("copyreg", "_reconstructor")] = _reconstructor
    allowed[("copy_reg", "_reconstructor")] = _reconstructor
    allowed[("_codecs", "encode")] = __import__("codecs").encode
    allowed[("collections", "OrderedDict")] = collections.OrderedDict
    # numpy's own reconstructors would trust the file's dtype and byte states (a crafted structured
    # dtype can smuggle a pointer into an "object" field): arrays are rebuilt here from plain numeric
    # states only (:class:`_PickledArray`), after the whole file is read.
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(module, "_reconstruct")] = _PickledArray
        allowed[(module, "scalar")] = _pickled_scalar
    allowed[("numpy", "dtype")] = _PickledDtype
    allowed[("numpy", "ndarray")] = _PickledArray
    try:
        import torch._utils
    except ImportError:  # without torch, tensors stay placeholders
        return allowed
    allowed[("torch._utils", "_rebuild_tensor_v2")] = torch._utils._rebuild_tensor_v2
    allowed[("torch._utils", "_rebuild_tensor")] = torch._utils._rebuild_tensor
    allowed[("torch.storage", "_load_from_bytes")] = _safe_load_from_bytes
    return allowed


class EpisodeUnpickler(pickle.Unpickler):
    """Unpickler that maps every global outside a harmless allow-list to a :class:`Placeholder`."""

    _allowed: dict[tuple[str, str], Any] | None = None

    def __init__(self, file: Any):
        super().__init__(file)
        if EpisodeUnpickler._allowed is None:
            EpisodeUnpickler._allowed = _safe_globals()
        self._placeholders: dict[tuple[str, str], type] = {}

    def find_class(self, module: str, name: str) -> Any:
        found = self._allowed.get((module, name))
        if found is not None:
            return found
        key = (module, name)
        if key not in self._placeholders:
            self._placeholders[key] = type(
                name, (Placeholder,), {"pickled_module": module, "pickled_name": name}
            )
        return self._placeholders[key]


@dataclass(frozen=True)
class RawEpisode:
    """One episode of a published pickle, as stored (scene and ids in the file's spelling)."""

    index: int
    scene: str
    target_type: str
    target_ids: tuple[str, ...]
    start: tuple[float, float, int, int]  # x, z, yaw, horizon
    room: str | None = None
    embedding: np.ndarray | None = field(default=None, repr=False, compare=False)


def _start_of(state: Any) -> tuple[float, float, int, int]:
    if isinstance(state, str):
        return parse_pose_key(state)
    values = state if isinstance(state, dict) else getattr(state, "__dict__", {})
    try:
        numbers = [values[k] for k in ("x", "z", "rotation", "horizon")]
        if not all(isinstance(v, int | float | np.number) for v in numbers):
            raise TypeError
        x, z, rotation, horizon = (float(v) for v in numbers)
        return round(x, 2), round(z, 2), round(rotation), round(horizon)
    except (KeyError, TypeError, ValueError, OverflowError):  # round() of inf or NaN included
        shown = state if isinstance(state, Placeholder | str) else type(state).__name__
        raise ValueError(f"start state {shown!r} has no finite x, z, rotation, horizon") from None


def _as_array(value: Any) -> np.ndarray | None:
    if value is None:
        return None
    import torch

    try:
        if isinstance(value, torch.Tensor):
            # Through the class, not the instance: a tensor's pickled state may set attributes on it.
            value = torch.Tensor.detach(value).cpu().to(torch.float64).numpy()
        return np.asarray(value, dtype=np.float64)
    except (
        TypeError,
        ValueError,
        RuntimeError,
        OverflowError,
    ):  # not numbers, ragged, huge, a dtype numpy lacks
        return None


def read_episode_file(path: str | Path) -> tuple[list[RawEpisode], list[tuple[int, str]]]:
    """Episodes of a SAVN/MJOLNIR/HOZ pickle, and ``(index, reason)`` of entries that are malformed."""
    path = Path(path)
    if not path.is_file():
        raise OfflineFormatError(path, "no such episode file")
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise OfflineFormatError(path, f"cannot be read ({error})") from None
    try:
        _check_opcodes(raw)
        data = _materialize(EpisodeUnpickler(io.BytesIO(raw)).load())
    except Exception as error:  # whatever the allowed constructors raise on crafted arguments
        raise OfflineFormatError(
            path, f"not a readable episode pickle ({type(error).__name__}: {str(error)[:200]})"
        ) from None
    if not isinstance(data, list | tuple):
        raise OfflineFormatError(path, f"expected a list of episode dicts, found {type(data).__name__}")
    episodes: list[RawEpisode] = []
    bad: list[tuple[int, str]] = []
    for i, entry in enumerate(data):
        if not isinstance(entry, dict):
            bad.append((i, f"entry is a {type(entry).__name__}, not a dict"))
            continue
        missing = [k for k in ("scene", "goal_object_type", "task_data", "state") if k not in entry]
        if missing:
            bad.append((i, f"entry has no {', '.join(missing)}"))
            continue
        try:
            start = _start_of(entry["state"])
        except ValueError as error:
            bad.append((i, str(error)))
            continue
        not_text = [k for k in ("scene", "goal_object_type") if not isinstance(entry[k], str)]
        if not_text or not isinstance(entry.get("room"), str | None):
            bad.append((i, f"entry's {', '.join(not_text) or 'room'} is not a string"))
            continue
        task = entry["task_data"]
        ids = (task,) if isinstance(task, str) else task if isinstance(task, list | tuple) else None
        if task is not None and (ids is None or not all(isinstance(t, str) for t in ids)):
            bad.append((i, f"task_data is not an object id or a list of object ids ({type(task).__name__})"))
            continue
        episodes.append(
            RawEpisode(
                index=i,
                scene=entry["scene"],
                target_type=entry["goal_object_type"],
                target_ids=tuple(ids or ()),
                start=start,
                room=entry.get("room"),
                embedding=_as_array(entry.get("glove_embedding")),
            )
        )
    return episodes, bad


# ---------------------------------------------------------------------------------------- mapping


@dataclass
class MappingReport:
    """Mapped episodes (``episode_id`` = ``import/<room>/<index in the file>``) and the skipped
    ones as ``(index in the file, reason)``."""

    episodes: list[Episode]
    skipped: list[tuple[int, str]]
    total: int
    exact_ids: int = 0
    nearest_ids: int = 0
    snapped_starts: int = 0

    @property
    def mapped(self) -> int:
        return len(self.episodes)

    def summary(self, max_reasons: int = 10) -> str:
        lines = [
            f"{self.mapped} of {self.total} episodes mapped, {len(self.skipped)} skipped",
            f"target ids: {self.exact_ids} matched verbatim, {self.nearest_ids} by type + nearest position",
            f"start poses: {self.snapped_starts} snapped to the nearest built-in pose",
        ]
        reasons = collections.Counter(_reason_kind(r) for _, r in self.skipped)
        for reason, count in reasons.most_common(max_reasons):
            example = next(f"#{i}: {r}" for i, r in self.skipped if _reason_kind(r) == reason)
            lines.append(f"  skipped {count}: {reason} (e.g. {example})")
        return "\n".join(lines)


def _reason_kind(reason: str) -> str:
    return reason.split(":", 1)[0]


def _id_type_and_position(object_id: str) -> tuple[str, tuple[float, float, float]]:
    """THOR ids are ``Type|x|y|z`` (+ ``|ChildType`` for sub-objects such as ``SinkBasin``)."""
    parts = object_id.split("|")
    if len(parts) < 4:
        raise ValueError(object_id)
    return object_type_of_id(object_id), (float(parts[1]), float(parts[2]), float(parts[3]))


def _v5_types(object_type: str) -> tuple[str, ...]:
    return (object_type, *TYPE_ALIASES.get(object_type, ()))


def map_episodes(
    episodes: Iterable[RawEpisode],
    *,
    scene_data: Callable[[str], SceneData] | None = None,
    max_target_distance: float = DEFAULT_MAX_TARGET_DISTANCE,
    max_start_distance: float = DEFAULT_MAX_START_DISTANCE,
    rotation_step: int = 45,
) -> MappingReport:
    """Map published episodes onto the built-in scenes.

    ``scene_data(name)`` supplies the built-in SceneData, whose poses the starts snap to; without
    it starts snap to the scene's reachable grid (``load_scene(name).reachable``), yaw and horizon
    unchanged.
    """
    from mapless.scenes import load_scene
    from mapless.scenes.catalogue import canonical_scene

    report = MappingReport(episodes=[], skipped=[], total=0)
    for episode in episodes:
        report.total += 1
        try:
            name = canonical_scene(episode.scene)
        except MaplessError:
            report.skipped.append((episode.index, f"unknown scene: {episode.scene!r}"))
            continue
        scene = load_scene(name)
        mapped, problem, exact = _map_targets(scene, episode.target_ids, max_target_distance)
        if problem:
            report.skipped.append((episode.index, problem))
            continue
        x, z, yaw, horizon = episode.start
        if yaw % rotation_step:
            report.skipped.append((episode.index, f"start yaw not on the {rotation_step} degree grid: {yaw}"))
            continue
        start, snapped = _snap_start(name, scene, x, z, yaw % 360, horizon, scene_data, max_start_distance)
        if start is None:
            report.skipped.append(
                (episode.index, f"start pose not reachable: {pose_key(x, z, yaw, horizon)} in {name}")
            )
            continue
        target_types = [scene.object(i).type for i in mapped]
        goal = next((t for t in _v5_types(episode.target_type) if t in target_types), target_types[0])
        optimal = -1
        if scene_data is not None:
            sd = scene_data(name)
            known = [sd.instance_ids.index(i) for i in mapped if i in sd.instance_ids]
            distance = int(
                sd.distances_to(sd.goal_mask_for_instances(np.array(known, dtype=np.int64)))[
                    sd.pose_index[pose_key(*start)]
                ]
            )
            if distance < 0:
                report.skipped.append(
                    (
                        episode.index,
                        f"target not reachable from the start: {mapped} from {pose_key(*start)} in {name}",
                    )
                )
                continue
            optimal = distance + 1
        report.exact_ids += exact
        report.nearest_ids += len(episode.target_ids) - exact
        report.snapped_starts += snapped
        report.episodes.append(
            Episode(
                scene=name,
                target=goal,
                start=start,
                optimal_length=optimal,
                target_ids=tuple(mapped),
                episode_id=f"import/{scene.room_type}/{episode.index:04d}",
            )
        )
    return report


def _map_targets(scene: Any, ids: tuple[str, ...], max_distance: float) -> tuple[list[str], str | None, int]:
    if not ids:
        return [], "no target: task_data is empty", 0
    mapped: list[str] = []
    exact = 0
    for object_id in ids:
        if object_id in scene.object_index:
            exact += 1
            mapped.append(object_id)
            continue
        try:
            object_type, (x, _, z) = _id_type_and_position(object_id)
        except ValueError:
            return [], f"target id without a position: {object_id!r}", 0
        candidates = [
            o for t in _v5_types(object_type) for o in (scene.objects[i] for i in scene.instances_of(t))
        ]
        if not candidates:
            return [], f"no object of that type in the scene: {object_type} ({object_id!r}, {scene.name})", 0
        best = min(candidates, key=lambda o: math.hypot(o.center[0] - x, o.center[2] - z))
        distance = math.hypot(best.center[0] - x, best.center[2] - z)
        if distance > max_distance:
            return (
                [],
                (
                    f"no object of that type nearby: nearest {best.id!r} is {distance:.2f} m from "
                    f"{object_id!r} ({scene.name})"
                ),
                0,
            )
        mapped.append(best.id)
    return list(dict.fromkeys(mapped)), None, exact


def _snap_start(
    name: str,
    scene: Any,
    x: float,
    z: float,
    yaw: int,
    horizon: int,
    scene_data: Callable[[str], SceneData] | None,
    max_distance: float,
) -> tuple[tuple[float, float, int, int] | None, bool]:
    key = pose_key(x, z, yaw, horizon)
    if scene_data is not None:
        sd = scene_data(name)
        if key in sd.pose_index:
            return (x, z, yaw, horizon), False
        same = np.flatnonzero((sd.yaw == yaw) & (sd.horizon == horizon))
        if not len(same):
            return None, False
        d = np.hypot(sd.x[same] - x, sd.z[same] - z)
        best = int(same[np.argmin(d)])
        if d.min() > max_distance:
            return None, False
        return (round(float(sd.x[best]), 2), round(float(sd.z[best]), 2), yaw, horizon), True
    grid = scene.reachable
    if not len(grid):
        return None, False
    d = np.hypot(grid[:, 0] - x, grid[:, 1] - z)
    best = int(np.argmin(d))
    if d[best] > max_distance:
        return None, False
    snapped = (round(float(grid[best, 0]), 2), round(float(grid[best, 1]), 2), yaw, horizon)
    return snapped, pose_key(*snapped) != key


def import_episode_file(path: str | Path, **kwargs: Any) -> MappingReport:
    """:func:`read_episode_file` then :func:`map_episodes`; malformed entries count as skipped."""
    episodes, bad = read_episode_file(path)
    report = map_episodes(episodes, **kwargs)
    report.skipped = sorted(bad + report.skipped)
    report.total += len(bad)
    return report


# ---------------------------------------------------------------------------------------- writing


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
