"""On-disk cache of built scenes.

A cache entry is ``<cache_dir>/<fingerprint>/<scene>.npz``. The fingerprint hashes every simulator
parameter, the simulator's version and the scene data file, so changing any of them selects a fresh
folder. Each file also stores its fingerprint and the checksum of its arrays; a file that does not
load, carries another fingerprint or fails the checksum is rebuilt, never used.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from importlib import resources
from pathlib import Path

import numpy as np

from mapless.files import replacing
from mapless.scenes.catalogue import canonical_scene
from mapless.scenes.layout import SCENE_FILE, load_scene
from mapless.sim.build import build_scene_data
from mapless.sim.config import SimConfig
from mapless.sim.scene_data import SceneData

#: Bump when the simulator's output changes for the same parameters.
SIM_VERSION = 1
_ARRAY_FIELDS = (
    "x", "z", "yaw", "horizon", "successors", "view_ptr", "view_instance", "view_box",
    "view_distance", "view_visible", "context", "features",
)  # fmt: skip


def default_cache_dir() -> Path:
    return Path(os.environ.get("MAPLESS_CACHE", Path.home() / ".cache" / "mapless")) / "scenes"


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


def cache_path(scene: str, config: SimConfig, cache_dir: Path | None = None) -> Path:
    return Path(cache_dir or default_cache_dir()) / fingerprint(config) / f"{canonical_scene(scene)}.npz"


def save(data: SceneData, path: Path, config: SimConfig) -> None:
    """Atomic write: a temporary file in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {name: getattr(data, name) for name in _ARRAY_FIELDS}
    header = {
        "fingerprint": fingerprint(config),
        "checksum": _checksum(arrays),
        "scene": data.scene,
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
    return SceneData(
        scene=header["scene"],
        room_type=header["room_type"],
        instance_ids=tuple(header["instance_ids"]),
        instance_types=tuple(header["instance_types"]),
        feature_scale=header["feature_scale"],
        meta=header["meta"],
        **arrays,
    )


def load_or_build(
    scene: str, config: SimConfig | None = None, cache_dir: Path | None = None, rebuild: bool = False
) -> SceneData:
    """The scene's data from the cache, building (and caching) it when missing, stale or corrupt."""
    config = config or SimConfig()
    path = cache_path(scene, config, cache_dir)
    if path.exists() and not rebuild:
        try:
            return load(path, config)
        except StaleCacheError:
            pass
    data = build_scene_data(load_scene(scene), config)
    save(data, path, config)
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
    load_or_build(scene, config, cache_dir, rebuild)
    return cache_path(scene, config, cache_dir)
