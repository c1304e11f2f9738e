"""``mapless/ObjectNav-v0``: the gymnasium environment with the package's scenes, training sampler
and evaluation protocols as its defaults, so that ``gym.make("mapless/ObjectNav-v0")`` needs no
argument (``import mapless`` registers it).

With no option it plays training episodes drawn as the trainers draw them (:class:`TrainingSampler`)
on the built-in training floor plans (x01-x20), under the ``standard`` protocol's success rule. Each
scene is loaded from the scene cache on first use, and built there first when missing (seconds per
scene), so a fresh machine starts without a ``mapless scenes build``. The keyword options:

* ``scenes``: the floor plans of sampled episodes, as ``env.scenes`` of a training config (a split
  such as ``train``, ``train:kitchen``, or comma-separated names such as ``FloorPlan25,FloorPlan401``);
* ``episodes``: a fixed list of :class:`Episode` instead, or the name of an evaluation split
  (``val``, ``test``; the protocol's sets: ``reference`` reads ``ref_val``/``ref_test``), played in
  order under the evaluation step limits;
* ``protocol``: ``standard``, ``paper`` or ``reference`` (:mod:`mapless.episodes.protocols`): the
  success rule, and the target set of sampled episodes unless ``target_set`` names one;
* ``render_mode="rgb_array"``: top-down frames (:meth:`NavEnv.render`);
* ``library``: a :class:`SceneLibrary` to share between environments (a vector environment's copies):
  built under ``protocol``'s success rule (an error otherwise, where the library says its settings),
  and in place of ``cache_dir``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym

from mapless import ENV_ID
from mapless.episodes import evalsets
from mapless.episodes.protocols import get_protocol, split_for
from mapless.episodes.sampler import TrainingSampler
from mapless.errors import MaplessError
from mapless.scenes.catalogue import resolve_scenes
from mapless.sim.config import SimConfig
from mapless.sim.env import NavEnv
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.task import RewardConfig


def scene_library(protocol: str = "standard", cache_dir: str | Path | None = None) -> SceneLibrary:
    """The built-in scenes under ``protocol``'s success rule, cached in ``cache_dir`` (default
    ``$MAPLESS_CACHE``, else ``~/.cache/mapless``)."""
    return SceneLibrary.builtin(
        get_protocol(protocol).sim(SimConfig()), Path(cache_dir) if cache_dir else None
    )


def fixed_episodes(split: str, protocol: str = "standard", target_set: str | None = None) -> list[Episode]:
    """The shipped evaluation episodes of ``split`` (``val`` or ``test``) under ``protocol``, those of
    the target set ``target_set`` (default: the protocol's)."""
    chosen = get_protocol(protocol)
    path = evalsets.builtin_path(split_for(protocol, split), target_set or chosen.target_set)
    return evalsets.load(path)[0]


class ObjectNavEnv(NavEnv):
    """:class:`NavEnv` built from keyword options, each with a default (the module's text)."""

    def __init__(
        self,
        scenes: str | Sequence[str] = "train",
        episodes: Sequence[Episode] | str | None = None,
        protocol: str = "standard",
        target_set: str | None = None,
        seed: int = 0,
        rewards: RewardConfig | None = None,
        max_steps: int | None = None,
        render_mode: str | None = None,
        render_size: int = 256,
        library: SceneLibrary | None = None,
        cache_dir: str | Path | None = None,
    ):
        chosen = get_protocol(protocol)
        target_set = target_set or chosen.target_set
        if library is not None:
            if cache_dir is not None:
                raise MaplessError(
                    "cache_dir is where the env builds its own library; give library or cache_dir"
                )
            if library.sim is not None and library.sim != chosen.sim(library.sim):
                raise MaplessError(
                    f"the library's scenes count success within {library.sim.visibility_distance} m, the "
                    f"{chosen.name} protocol within {chosen.sim(library.sim).visibility_distance} m: "
                    f"build it with scene_library({chosen.name!r})"
                )
        library = library or scene_library(protocol, cache_dir)
        sampler = None
        if isinstance(episodes, str):
            episodes = fixed_episodes(episodes, protocol, target_set)
        if episodes is None:
            sampler = TrainingSampler(library, resolve_scenes(scenes), target_set, seed=seed)
        super().__init__(
            library,
            episodes=None if episodes is None else list(episodes),
            sampler=sampler,
            rewards=rewards,
            mode="train" if episodes is None else "eval",
            max_steps=max_steps,
            render_mode=render_mode,
            render_size=render_size,
        )
        self.protocol = chosen


def make_env(**options) -> gym.Env:
    """``gym.make("mapless/ObjectNav-v0", **options)``: the environment inside gymnasium's usual
    wrappers (the options are :class:`ObjectNavEnv`'s)."""
    return gym.make(ENV_ID, **options)


def make_vec_env(n: int, asynchronous: bool = False, **options) -> gym.vector.VectorEnv:
    """``n`` copies of the environment as one gymnasium vector environment: in this process
    (``SyncVectorEnv``, the copies sharing one scene library, so each scene is loaded once) or one
    process each (``AsyncVectorEnv``). Each copy's sampler gets its own seed (``seed`` + its index),
    so that the copies do not walk through the room types in step."""
    if n < 1:
        raise MaplessError(f"make_vec_env needs at least one environment, got {n}")
    seed = options.pop("seed", 0)
    if not asynchronous and "library" not in options:
        options["library"] = scene_library(options.get("protocol", "standard"), options.get("cache_dir"))

    def one(index: int):
        return lambda: gym.make(ENV_ID, seed=seed + index, **options)

    fns = [one(i) for i in range(n)]
    return gym.vector.AsyncVectorEnv(fns) if asynchronous else gym.vector.SyncVectorEnv(fns)
