"""Gymnasium environment: one ObjectNav episode at a time in a precomputed scene.

Registered as ``mapless/ObjectNav-v0``. Observation space (docs/observations.md):

* ``context`` Box float32 ``[C, 4]``: per category ``[in view, x_c, y_c, union-box area]``
* ``features`` Box float32 ``[C + 3, 7, 7]``: semantic feature map
* ``target_embedding`` Box float32 ``[300]``: GloVe vector of the target
* ``target_index`` Box int64 ``[]``: the target's row in the category set (-1 if none)

Actions: Discrete(6) = MoveAhead, RotateLeft, RotateRight, LookUp, LookDown, Done. The episode
terminates on ``Done`` (success iff a target instance is visible) and is truncated at the step
limit. ``info`` carries ``success``, ``optimal_length``, ``visited`` (pose ids so far),
``failed_action`` and ``pose`` (pose id; ``env.data.key(pose)`` gives the SAVN pose key).
"""

from __future__ import annotations

from typing import ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mapless.errors import MaplessError
from mapless.knowledge.parents import parent_reward
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import ACTIONS, DONE
from mapless.sim.task import (
    RewardConfig,
    TargetFields,
    check_scene_categories,
    max_steps_for,
    resolve_target_fields,
)

ENV_ID = "mapless/ObjectNav-v0"


class NavEnv(gym.Env):
    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(
        self,
        library: SceneLibrary,
        episodes: list[Episode] | None = None,
        sampler=None,
        targets: TargetFields | None = None,
        rewards: RewardConfig | None = None,
        mode: str = "train",
        max_steps: int | None = None,
        category_set: str | None = None,
    ):
        if episodes is None and sampler is None:
            raise MaplessError("NavEnv needs a list of episodes or an episode sampler")
        self.library = library
        self.episodes = episodes
        self.sampler = sampler
        self.targets = resolve_target_fields(targets, category_set)
        self.rewards = rewards or RewardConfig()
        self.mode = mode
        self.fixed_max_steps = max_steps
        n_cat = len(self.targets.categories)
        self.action_space = spaces.Discrete(len(ACTIONS))
        self.observation_space = spaces.Dict(
            {
                "context": spaces.Box(0.0, 1.0, (n_cat, 4), np.float32),
                "features": spaces.Box(0.0, 1.0, (n_cat + 3, 7, 7), np.float32),
                "target_embedding": spaces.Box(-np.inf, np.inf, (300,), np.float32),
                "target_index": spaces.Box(-1, n_cat - 1, (), np.int64),
            }
        )
        self._next_fixed = 0
        self._scene_name: str | None = None
        self._features: np.ndarray | None = None
        self._goal_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    # -- episode bookkeeping -------------------------------------------------------------------
    def _select_episode(self, options: dict | None) -> Episode:
        if options and "episode" in options:
            return options["episode"]
        if self.episodes is not None:
            episode = self.episodes[self._next_fixed % len(self.episodes)]
            self._next_fixed += 1
            return episode
        return self.sampler.sample(self.np_random)

    def _load_scene(self, scene: str) -> None:
        if scene != self._scene_name:
            self.data = self.library[scene]
            check_scene_categories(self.data, self.targets)
            # One float32 copy per scene keeps each step a view, not a conversion.
            self._features = self.data.features.astype(np.float32) * np.float32(self.data.feature_scale)
            self._context = self.data.context
            self._successors = self.data.successors
            self._scene_name = scene

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode = self._select_episode(options)
        self.library.check_target(episode.scene, episode.target)
        self._load_scene(episode.scene)
        self.episode = episode
        self.pose = self.library.pose_of(episode.scene, episode.start)
        self._goal, distances = self._goal_and_distances(episode)
        self._target_embedding = self.targets.embedding(episode.target)
        self._target_index = np.array(self.targets.index(episode.target), dtype=np.int64)
        self._parent_weights = self.targets.parent_weights(self.data.room_type, episode.target)
        self._pays_parents = self.rewards.pays_parent_reward(self.data.room_type)
        self._seen_parents = np.zeros_like(self._parent_weights, dtype=bool)
        self.max_steps = self.fixed_max_steps or max_steps_for(self.data.room_type, self.mode)
        self.steps = 0
        self.visited = [self.pose]
        self.optimal_length = episode.optimal_length
        if self.optimal_length < 0:
            d = int(distances[self.pose])
            self.optimal_length = d + 1 if d >= 0 else -1
        return self._observation(), self._info(success=False, failed=False)

    def _goal_and_distances(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        key = (episode.scene, episode.target, episode.target_ids)
        if key not in self._goal_cache:
            instances = self.data.goal_instances(episode.target, episode.target_ids)
            goal = self.data.goal_mask_for_instances(instances)
            self._goal_cache[key] = (goal, self.data.distances_to(goal))
        return self._goal_cache[key]

    def _observation(self) -> dict:
        return {
            "context": self._context[self.pose],
            "features": self._features[self.pose],
            "target_embedding": self._target_embedding,
            "target_index": self._target_index,
        }

    def _info(self, success: bool, failed: bool) -> dict:
        return {
            "success": success,
            "optimal_length": self.optimal_length,
            "visited": self.visited,
            "failed_action": failed,
            "pose": self.pose,
            "episode": self.episode,
        }

    def step(self, action: int):
        action = int(action)
        self.steps += 1
        reward = self.rewards.step_penalty
        success = failed = False
        if action == DONE:
            success = bool(self._goal[self.pose])
            if success:
                reward = self.rewards.success_reward
            terminated = True
        else:
            nxt = int(self._successors[self.pose, action])
            failed = nxt == self.pose
            self.pose = nxt
            self.visited.append(nxt)
            terminated = False
            if self._pays_parents:
                bonus, self._seen_parents = parent_reward(
                    self._context[nxt, :, 0] > 0, self._parent_weights, self._seen_parents
                )
                if bonus > 0:
                    reward = float(bonus)
        truncated = not terminated and self.steps >= self.max_steps
        return self._observation(), reward, terminated, truncated, self._info(success, failed)


gym.register(id=ENV_ID, entry_point="mapless.sim.env:NavEnv")
