"""A process-wide store of loaded :class:`SceneData`, keyed by scene name."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mapless.errors import MaplessError, UnknownNameError
from mapless.sim.config import SimConfig
from mapless.sim.scene_data import SceneData


class SceneLibrary:
    """Loads scenes on first use through ``loader`` and keeps them (all of iTHOR fits in memory:
    about 1 GB of uint8 feature maps for the 120 scenes). ``sim``: the simulator settings its scenes
    are built with, where known (the built-in library's), so that a user of the library can check
    them against the success rule it expects."""

    def __init__(
        self,
        loader: Callable[[str], SceneData],
        preparer: Callable[[list[str], bool], object] | None = None,
        sim: SimConfig | None = None,
    ):
        self._loader = loader
        self._preparer = preparer
        self._scenes: dict[str, SceneData] = {}
        self.sim = sim

    @classmethod
    def builtin(cls, config: SimConfig | None = None, cache_dir: Path | None = None) -> SceneLibrary:
        from mapless.sim.cache import build_many, load_or_build

        config = config or SimConfig()
        return cls(
            lambda name: load_or_build(name, config, cache_dir),
            lambda scenes, progress: build_many(
                scenes, config, cache_dir, progress=progress, missing_only=True
            ),
            sim=config,
        )

    def prepare(self, scenes: Sequence[str], progress: bool = True) -> None:
        """Get ``scenes`` ready before work starts. The built-in library builds the missing caches
        in parallel, with a progress bar; left to first use, a fresh machine would build them one
        at a time, silently, minutes into a run. Other libraries have nothing to prepare."""
        if self._preparer is not None:
            self._preparer(list(scenes), progress)

    def __getitem__(self, scene: str) -> SceneData:
        if scene not in self._scenes:
            self._scenes[scene] = self._loader(scene)
        return self._scenes[scene]

    def check_target(self, scene: str, target: str) -> None:
        """An episode's target must exist in its scene; the error lists the scene's object types."""
        data = self[scene]
        if target not in data.instance_types:
            raise UnknownNameError(f"target type in {scene}", target, sorted(set(data.instance_types)))

    def pose_of(self, scene: str, start: tuple[float, float, int, int]) -> int:
        """Pose id of ``(x, z, yaw, horizon)``; an off-grid pose is an error naming the nearest one."""
        data = self[scene]
        x, z, yaw, horizon = start
        from mapless.sim.scene_data import pose_key

        key = pose_key(x, z, yaw, horizon)
        if key in data.pose_index:
            return data.pose_index[key]
        cost = (
            np.hypot(data.x - x, data.z - z)
            + 0.01 * (data.yaw != int(yaw) % 360)
            + 0.01 * (data.horizon != int(horizon))
        )
        nearest = int(np.argmin(cost))
        raise MaplessError(
            f"pose {key} is not on the reachable grid of {scene}; nearest valid pose: {data.key(nearest)}"
        )
