"""Training-episode sampling as SAVN and MJOLNIR do it (``BasicEpisode._new_episode``):

1. room types are shuffled once per worker and cycled, one episode each;
2. the scene is uniform over the split's scenes of that room type;
3. the start is a uniform (position, yaw) with horizon 0;
4. the target type is drawn uniformly over the *instances* of the room's targets that are visible
   from some pose of the scene (so types are weighted by instance count), and every instance of
   that type counts for success.

The references check neither that the target is reachable nor that it is not already visible at
the start; in their data every pose is reachable from every other (BFS-generated from one start),
so with a visible target drawn, no start is unwinnable. Here a few scenes have pose-graph islands
(``SceneData.usable_poses``), so the start is drawn uniformly over the usable horizon-0 poses from
which the target is reachable: in a scene without islands those are all its horizon-0 poses, and
the draws are the references' (and those of earlier versions of this sampler) exactly.

With scene variants (``env.layouts``), step 2 is followed by one more draw: with probability
``variant_fraction`` the episode is played on one of the floor plan's variants, uniformly. Without
them no draw is added, so the default-arrangement protocol samples what it always sampled.
"""

from __future__ import annotations

import numpy as np

from mapless.scenes.catalogue import ROOM_TYPES, room_type_of
from mapless.scenes.categories import targets
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary


class TrainingSampler:
    def __init__(
        self,
        library: SceneLibrary,
        scenes: list[str],
        target_set: str = "mjolnir22",
        seed: int = 0,
        variants: dict[str, list[str]] | None = None,
        variant_fraction: float = 0.0,
    ):
        self.library = library
        self.variants = {s: v for s, v in (variants or {}).items() if v}
        self.variant_fraction = variant_fraction if self.variants else 0.0
        self.targets = targets(target_set)
        self.scenes_by_room = {r: [s for s in scenes if room_type_of(s) == r] for r in ROOM_TYPES}
        self.room_cycle = [r for r in ROOM_TYPES if self.scenes_by_room[r]]
        if not self.room_cycle:
            raise ValueError("TrainingSampler needs at least one scene")
        rng = np.random.default_rng(seed)
        rng.shuffle(self.room_cycle)
        self.position = 0  # episodes sampled so far: where the room cycle stands (checkpointed)
        self._candidates: dict[str, np.ndarray] = {}
        self._starts: dict[tuple[str, str], np.ndarray] = {}

    def _target_instances(self, scene: str) -> np.ndarray:
        """Instance types of the room's targets visible from some pose that a usable start reaches."""
        if scene not in self._candidates:
            data = self.library[scene]
            _, visible_instances = data.visible_matrix_csr
            seen = np.unique(visible_instances)
            wanted = set(self.targets[data.room_type])
            types = [data.instance_types[i] for i in seen if data.instance_types[i] in wanted]
            # A type visible only from an island has no start: never drawn (an unwinnable episode).
            self._candidates[scene] = np.array([t for t in types if len(self._start_poses(scene, t))])
        return self._candidates[scene]

    def _start_poses(self, scene: str, target: str) -> np.ndarray:
        """Horizon-0 poses of the usable component from which ``target`` is reachable."""
        if (scene, target) not in self._starts:
            data = self.library[scene]
            ok = (data.horizon == 0) & data.usable_poses & (data.target_distances(target) >= 0)
            self._starts[scene, target] = np.flatnonzero(ok)
        return self._starts[scene, target]

    def sample(self, rng: np.random.Generator) -> Episode:
        room = self.room_cycle[self.position % len(self.room_cycle)]
        self.position += 1
        scenes = self.scenes_by_room[room]
        for _ in range(100):
            scene = scenes[rng.integers(len(scenes))]
            if self.variant_fraction and scene in self.variants and rng.random() < self.variant_fraction:
                scene = self.variants[scene][rng.integers(len(self.variants[scene]))]
            types = self._target_instances(scene)
            if len(types) == 0:
                continue
            target = str(types[rng.integers(len(types))])
            starts = self._start_poses(scene, target)
            start = int(starts[rng.integers(len(starts))])
            return Episode(scene=scene, target=target, start=self.library[scene].pose_tuple(start))
        raise RuntimeError(f"no valid training episode found in {room} scenes {scenes}")
