"""On-disk cache of built scenes.

A cache entry is ``<root>/scenes/<fingerprint>/<scene>.npz``, where the root is ``--cache-dir``
(``env.cache_dir``), else ``$MAPLESS_CACHE``, else ``~/.cache/mapless``: the option and the variable
name the same folder, so one cache serves both. A scene variant (mapless.scenes.variants) is
``<scene>@<hash>.npz``, the hash over its arrangement's content. The fingerprint hashes every simulator parameter,
the simulator's version and the scene data file, so changing any of them selects a fresh folder.
Each file also stores its fingerprint, its scene and the checksum of its arrays; a file that does
not load, carries another fingerprint or scene or fails the checksum is rebuilt, never used.

A cache that cannot be written (read-only, a folder in the way) does not waste the build: the scene
is used from memory with a warning; ``mapless scenes build``, whose only job is to write the cache,
refuses it up front instead.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from mapless.errors import MaplessError
from mapless.files import replacing, unwritable
from mapless.scenes.catalogue import canonical_scene
from mapless.scenes.floor_plans import SCENE_FILE
from mapless.scenes.layout import load_scene
from mapless.scenes.variants import cache_stem
from mapless.sim.build import build_scene_data
from mapless.sim.config import SimConfig
from mapless.sim.scene_data import SceneData

#: Bump when the simulator's output changes for the same parameters.
SIM_VERSION = 1
#: The arrays of a cache file and the dtypes build_scene_data gives them (a file with another is
#: not one it wrote).
_ARRAY_DTYPES = {
    "x": np.float32, "z": np.float32, "yaw": np.int16, "horizon": np.int16, "successors": np.int32,
    "view_ptr": np.int64, "view_instance": np.int32, "view_box": np.float32,
    "view_distance": np.float32, "view_visible": np.bool_, "context": np.float32, "features": np.uint8,
}  # fmt: skip
_ARRAY_FIELDS = tuple(_ARRAY_DTYPES)


def scenes_dir(cache_dir: str | Path | None = None) -> Path:
    """The scene folder of the cache root ``cache_dir`` (default ``$MAPLESS_CACHE``, else
    ``~/.cache/mapless``): ``<root>/scenes``."""
    root = cache_dir or os.environ.get("MAPLESS_CACHE") or Path.home() / ".cache" / "mapless"
    return Path(root) / "scenes"


class CacheError(MaplessError):
    """The scene cache cannot be written where it must be (``mapless scenes build``)."""


@functools.cache
def _scene_file_digest() -> str:
    return hashlib.sha256(resources.files("mapless.data").joinpath(SCENE_FILE).read_bytes()).hexdigest()


#: Fields added after caches and episode files were made: hashed only when they differ from their
#: default, so that adding one keeps every fingerprint made before it (and the shipped episode sets).
_LATER_FIELDS = {"strict_diagonals": False}


def fingerprint(config: SimConfig) -> str:
    sim = {k: v for k, v in config.as_dict().items() if _LATER_FIELDS.get(k, object()) != v}
    payload = json.dumps({"sim": sim, "version": SIM_VERSION, "data": _scene_file_digest()}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    digest = hashlib.sha256()
    for name in _ARRAY_FIELDS:
        digest.update(np.ascontiguousarray(arrays[name]).tobytes())
    return digest.hexdigest()


def cache_path(scene: str, config: SimConfig, cache_dir: str | Path | None = None) -> Path:
    """Where ``scene``'s file lives under the cache root ``cache_dir`` (see :func:`scenes_dir`)."""
    return scenes_dir(cache_dir) / fingerprint(config) / f"{cache_stem(canonical_scene(scene))}.npz"


def save(data: SceneData, path: Path, config: SimConfig) -> None:
    """Atomic write: a temporary file in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {name: getattr(data, name) for name in _ARRAY_FIELDS}
    header = {
        "fingerprint": fingerprint(config),
        "checksum": _checksum(arrays),
        "scene": path.stem,  # what load() checks; a variant's file is named by its arrangement's hash
        "room_type": data.room_type,
        "instance_ids": list(data.instance_ids),
        "instance_types": list(data.instance_types),
        "feature_scale": data.feature_scale,
        "meta": data.meta,
    }
    with replacing(path) as tmp, tmp.open("wb") as handle:  # a handle: a path would gain ".npz"
        np.savez_compressed(handle, header=np.array(json.dumps(header)), **arrays)


class StaleCacheError(Exception):
    """The cache file is unreadable, for other parameters, or corrupt."""


def load(path: Path, config: SimConfig) -> SceneData:
    try:
        with np.load(path, allow_pickle=False) as npz:
            header = json.loads(str(npz["header"]))
            arrays = {name: npz[name] for name in _ARRAY_FIELDS}
        if not isinstance(header, dict):
            raise ValueError("the header is not a mapping")
    except Exception as error:  # any failure to read (zlib, zip, json, ...) means a corrupt file
        raise StaleCacheError(f"{path}: unreadable ({type(error).__name__}: {error})") from error
    if header.get("fingerprint") != fingerprint(config):
        raise StaleCacheError(f"{path}: built with other simulator parameters")
    if header.get("scene") != path.stem:
        raise StaleCacheError(f"{path}: holds scene {header.get('scene')!r}, not {path.stem!r}")
    if header.get("checksum") != _checksum(arrays):
        raise StaleCacheError(f"{path}: checksum mismatch")
    try:
        problem = _inconsistency(header, arrays)
    except (TypeError, ValueError, IndexError):  # 0-d or non-numeric arrays
        problem = "arrays of unexpected shapes or types"
    if problem:  # a crafted file: the checksum covers the arrays, not what they must agree on
        raise StaleCacheError(f"{path}: {problem}")
    return SceneData(
        scene=header["scene"],
        room_type=header["room_type"],
        instance_ids=tuple(header["instance_ids"]),
        instance_types=tuple(header["instance_types"]),
        feature_scale=header["feature_scale"],
        meta=header["meta"],
        **arrays,
    )


def _inconsistency(header: dict, arrays: dict[str, np.ndarray]) -> str | None:
    """What is wrong with a cache file whose checksum holds, or None: header fields of the wrong
    type, or arrays whose sizes and indices disagree (they would fail mid-episode, not here)."""
    kinds = {
        "room_type": str,
        "instance_ids": list,
        "instance_types": list,
        "feature_scale": float,
        "meta": dict,
    }
    wrong = [k for k, kind in kinds.items() if not isinstance(header.get(k), kind)]
    if wrong:
        return f"header field {wrong[0]!r} is missing or not a {kinds[wrong[0]].__name__}"
    if not 0 < header["feature_scale"] <= 1:  # NaN included: 1/255 for uint8 features, 1 for float ones
        return f"feature_scale {header['feature_scale']} is not in (0, 1]"
    ids, types = header["instance_ids"], header["instance_types"]
    if len(ids) != len(types) or not all(isinstance(t, str) for t in ids + types):
        return "instance ids and types are not two lists of names of one length"
    wrong = [k for k, dtype in _ARRAY_DTYPES.items() if arrays[k].dtype != dtype]
    if wrong:
        return f"array {wrong[0]!r} is {arrays[wrong[0]].dtype}, not {np.dtype(_ARRAY_DTYPES[wrong[0]])}"
    poses = len(arrays["x"])
    ptr, entries = arrays["view_ptr"], len(arrays["view_instance"])
    checks = (
        all(arrays[k].shape == (poses,) for k in ("x", "z", "yaw", "horizon")),
        arrays["successors"].ndim == 2 and arrays["successors"].shape[0] == poses,
        arrays["successors"].size == 0
        or 0 <= arrays["successors"].min() <= arrays["successors"].max() < poses,
        ptr.shape == (poses + 1,) and ptr[0] == 0 and ptr[-1] == entries and bool(np.all(np.diff(ptr) >= 0)),
        entries == 0 or 0 <= arrays["view_instance"].min() <= arrays["view_instance"].max() < len(ids),
        arrays["view_box"].shape == (entries, 4),
        arrays["view_distance"].shape == arrays["view_visible"].shape == (entries,),
        arrays["context"].ndim == 3 and arrays["context"].shape[0] == poses,
        arrays["features"].ndim == 4 and arrays["features"].shape[0] == poses,
    )
    return None if all(checks) else "arrays of inconsistent sizes or indices"


def load_or_build(
    scene: str,
    config: SimConfig | None = None,
    cache_dir: str | Path | None = None,
    rebuild: bool = False,
    must_write: bool = False,
) -> SceneData:
    """The scene's data from the cache, building (and caching) it when missing, stale or corrupt.

    A file that cannot be written (a read-only cache, a folder where the file should be, the cache
    deleted under the build) leaves the built scene in memory with a warning, or raises
    :class:`CacheError` when ``must_write``."""
    config = config or SimConfig()
    path = cache_path(scene, config, cache_dir)
    if path.exists() and not rebuild:
        try:
            data = load(path, config)
        except StaleCacheError:
            pass
        else:  # a variant's file may hold the same arrangement under another name
            name = canonical_scene(scene)
            return data if data.scene == name else dataclasses.replace(data, scene=name)
    data = build_scene_data(load_scene(scene), config)
    try:
        save(data, path, config)
    except OSError as error:
        problem = (
            f"cannot write the scene cache file {path} ({type(error).__name__}: {error.strerror or error})"
        )
        if must_write:
            raise CacheError(
                f"{problem}; make the folder writable or choose another with --cache-dir"
            ) from None
        warnings.warn(f"{problem}; {scene} is kept in memory and will be built again next time", stacklevel=2)
    return data


def build_many(
    scenes: list[str],
    config: SimConfig,
    cache_dir: Path | None = None,
    workers: int = 2,
    rebuild: bool = False,
    progress: bool = True,
    missing_only: bool = False,
) -> list[Path]:
    """Build (or verify) the cache of many scenes in ``workers`` spawned processes.

    ``missing_only`` skips the scenes that have a file without reading it: a stale or corrupt file
    is left to :func:`load_or_build`, which rebuilds it on first use. That is rare (the fingerprint
    is in the folder name), while a fresh machine misses every scene.
    """
    import multiprocessing as mp

    from tqdm import tqdm

    if missing_only:
        scenes = [s for s in dict.fromkeys(scenes) if not cache_path(s, config, cache_dir).exists()]
    if not scenes:
        return []
    folder = cache_path(scenes[0], config, cache_dir).parent
    problem = unwritable(folder)
    if problem is not None:  # checked before the minutes of ray casting, not after
        message = f"the scene cache {folder} is not writable ({problem})"
        if not missing_only:
            raise CacheError(f"{message}; choose another folder with --cache-dir or $MAPLESS_CACHE")
        warnings.warn(f"{message}; each scene is built in memory when first used", stacklevel=2)
        return []
    jobs = [(s, config, cache_dir, rebuild) for s in scenes]
    bar = tqdm(total=len(jobs), desc="building scenes", unit="scene", disable=not progress)
    paths = []
    if workers <= 1:
        for job in jobs:
            paths.append(_build_job(job))
            bar.update()
    else:
        with mp.get_context("spawn").Pool(workers) as pool:
            for path in pool.imap_unordered(_build_job, jobs):
                paths.append(path)
                bar.update()
    bar.close()
    return paths


def _build_job(job: tuple) -> Path:
    scene, config, cache_dir, rebuild = job
    load_or_build(scene, config, cache_dir, rebuild, must_write=True)
    return cache_path(scene, config, cache_dir)
