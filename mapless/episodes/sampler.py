"""Training-episode sampling as SAVN and MJOLNIR do it (``BasicEpisode._new_episode``):

1. room types are shuffled once per worker and cycled, one episode each;
2. the scene is uniform over the split's scenes of that room type;
3. the start is a uniform (position, yaw) with horizon 0;
4. the target type is drawn uniformly over the *instances* of the room's targets that are visible
   from some pose of the scene (so types are weighted by instance count), and every instance of
   that type counts for success.

The references neither check that the target is reachable nor that it is not already visible at
the start; ``require_reachable`` adds the first check (off by default, for fidelity).
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
        require_reachable: bool = False,
    ):
        self.library = library
        self.targets = targets(target_set)
        self.require_reachable = require_reachable
        self.scenes_by_room = {r: [s for s in scenes if room_type_of(s) == r] for r in ROOM_TYPES}
        self.room_cycle = [r for r in ROOM_TYPES if self.scenes_by_room[r]]
        if not self.room_cycle:
            raise ValueError("TrainingSampler needs at least one scene")
        rng = np.random.default_rng(seed)
        rng.shuffle(self.room_cycle)
        self.position = 0  # episodes sampled so far: where the room cycle stands (checkpointed)
        self._candidates: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def _target_instances(self, scene: str) -> tuple[np.ndarray, np.ndarray]:
        """Instance types of the room's targets visible from at least one pose, and start poses."""
        if scene not in self._candidates:
            data = self.library[scene]
            _, visible_instances = data.visible_matrix_csr
            seen = np.unique(visible_instances)
            wanted = set(self.targets[data.room_type])
            types = np.array([data.instance_types[i] for i in seen if data.instance_types[i] in wanted])
            starts = np.flatnonzero(data.horizon == 0)
            self._candidates[scene] = (types, starts)
        return self._candidates[scene]

    def sample(self, rng: np.random.Generator) -> Episode:
        room = self.room_cycle[self.position % len(self.room_cycle)]
        self.position += 1
        scenes = self.scenes_by_room[room]
        for _ in range(100):
            scene = scenes[rng.integers(len(scenes))]
            types, starts = self._target_instances(scene)
            if len(types) == 0:
                continue
            target = str(types[rng.integers(len(types))])
            data = self.library[scene]
            start = int(starts[rng.integers(len(starts))])
            if self.require_reachable and data.target_distances(target)[start] < 0:
                continue
            return Episode(
                scene=scene,
                target=target,
                start=data.pose_tuple(start),
            )
        raise RuntimeError(f"no valid training episode found in {room} scenes {scenes}")
