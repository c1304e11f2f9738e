"""Fixture scenes and episodes for evaluator tests (hand-made SceneData, no simulator build)."""

from __future__ import annotations

import functools

import numpy as np
from scene_fixtures import grid_scene

from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary

#: A kitchen and a living room (200-step limit) on 7x7 grids with a blocked diagonal.
SCENES = {"FloorPlan5": "kitchen", "FloorPlan205": "living_room"}
GRID = tuple((0.25 * i, 0.25 * j) for i in range(7) for j in range(7))


@functools.cache
def _scene(name: str):
    """The fixture's random visibility, restricted to the far corner so that optimal paths are long."""
    data = grid_scene(positions=GRID, scene=name, room_type=SCENES[name], seed=len(name))
    poses = np.repeat(np.arange(data.n_poses), np.diff(data.view_ptr))
    corner = (data.x[poses] >= 1.25) & (data.z[poses] >= 1.25)
    data.view_visible = data.view_visible & corner
    return data


def fixture_library() -> SceneLibrary:
    """Picklable by reference (``eval_fixtures:fixture_library``) for spawn workers."""
    return SceneLibrary(_scene)


def fixture_episodes(per_scene: int = 12, seed: int = 0) -> list[Episode]:
    """Reachable, not-yet-visible episodes with stored optimal lengths (as the eval sets store them)."""
    rng = np.random.default_rng(seed)
    library = fixture_library()
    episodes = []
    for name in SCENES:
        data = library[name]
        made = 0
        while made < per_scene:
            target = ("Mug", "Toaster", "DiningTable")[rng.integers(3)]
            start = int(rng.choice(np.flatnonzero(data.horizon == 0)))
            d = int(data.target_distances(target)[start])
            if d <= 0:
                continue
            episodes.append(
                Episode(
                    scene=name,
                    target=target,
                    start=(float(data.x[start]), float(data.z[start]), int(data.yaw[start]), 0),
                    optimal_length=d + 1,
                    episode_id=f"{name}/{made}",
                )
            )
            made += 1
    return episodes
