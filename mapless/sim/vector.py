"""Batched environment: many ObjectNav episodes stepped at once with numpy. It is the one
implementation of the task's step rules (reward, parent bonus, success, truncation); the gymnasium
:class:`~mapless.sim.env.NavEnv` plays a batch of one.

All scenes given at construction are concatenated into global pose-indexed arrays, so a step of
``B`` episodes in any mix of scenes is a handful of vectorised gathers. Observations are gathered
only for the keys a model asks for (:meth:`observe`), since the feature map is the costly one.

Slots whose episode ended stay frozen (actions ignored, ``done`` True) until :meth:`reset` gives
them a new episode, which suits lockstep rollouts of whole episodes (the meta-learning trainers).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from mapless.actions import DONE, N_MOVEMENT_ACTIONS
from mapless.knowledge.parents import parent_reward
from mapless.observations import OBSERVATION_KEYS
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import SceneData
from mapless.sim.task import (
    RewardConfig,
    TargetFields,
    check_scene_categories,
    max_steps_for,
    resolve_target_fields,
)


@dataclass
class BatchStep:
    """Result of one batched step (arrays of length ``B``)."""

    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    failed_action: np.ndarray
    active: np.ndarray  # the slot took this step (it was not already done)


class BatchedNavEnv:
    def __init__(
        self,
        library: SceneLibrary,
        scenes: list[str],
        batch_size: int,
        targets: TargetFields | None = None,
        rewards: RewardConfig | None = None,
        mode: str = "train",
        max_steps: int | None = None,
        category_set: str | None = None,
    ):
        self.library = library
        self.batch_size = batch_size
        self.targets = resolve_target_fields(targets, category_set)
        self.rewards = rewards or RewardConfig()
        self.mode = mode
        self.fixed_max_steps = max_steps
        self.scene_names = list(dict.fromkeys(scenes))
        datas = [library[s] for s in self.scene_names]
        for data in datas:
            check_scene_categories(data, self.targets)
        self.scene_offset = dict(
            zip(self.scene_names, np.cumsum([0] + [d.n_poses for d in datas[:-1]]), strict=True)
        )
        self.successors = np.concatenate(
            [
                d.successors.astype(np.int64) + self.scene_offset[s]
                for s, d in zip(self.scene_names, datas, strict=True)
            ]
        )
        self.context = np.concatenate([d.context for d in datas])
        self._datas = datas
        self.feature_scale = np.float32(datas[0].feature_scale)
        self.n_poses = len(self.successors)
        self._goal_ids: dict[tuple, int] = {}
        self._goal_keys = np.zeros(0, dtype=np.int64)  # sorted goal_id * n_poses + global pose
        n_cat = len(self.targets.categories)
        b = batch_size
        self.pose = np.zeros(b, dtype=np.int64)
        self.goal = np.zeros(b, dtype=np.int64)
        self.steps = np.zeros(b, dtype=np.int64)
        self.max_steps = np.full(b, 1, dtype=np.int64)
        self.done = np.ones(b, dtype=bool)
        self.target_embedding = np.zeros((b, 300), dtype=np.float32)
        self.target_index = np.full(b, -1, dtype=np.int64)
        self.optimal_length = np.full(b, -1, dtype=np.int64)
        #: per slot, the BFS distance (in moves) from each of its scene's poses to the target's
        #: goal poses, for the shortest-path expert (None: unknown, e.g. instance-restricted targets)
        self._distances: list[np.ndarray | None] = [None] * b
        #: per slot, the distances the progress reward measures (None while that reward is off)
        self._progress_distances: list[np.ndarray | None] = [None] * b
        self.seen_parents = np.zeros((b, n_cat), dtype=bool)
        self.parent_weights = np.zeros((b, n_cat), dtype=np.float32)
        self.episodes: list[Episode | None] = [None] * b

    def _goal_id(self, episode: Episode) -> int:
        key = (episode.scene, episode.target, episode.target_ids)
        if key not in self._goal_ids:
            data = self.library[episode.scene]
            instances = data.goal_instances(episode.target, episode.target_ids)
            goal_poses = (
                np.flatnonzero(data.goal_mask_for_instances(instances)) + self.scene_offset[episode.scene]
            )
            gid = len(self._goal_ids)
            self._goal_ids[key] = gid
            self._goal_keys = np.union1d(self._goal_keys, gid * self.n_poses + goal_poses)
        return self._goal_ids[key]

    def reset(self, slots: np.ndarray | list[int], episodes: list[Episode]) -> None:
        """Start ``episodes`` in ``slots``."""
        for slot, episode in zip(slots, episodes, strict=True):
            if episode.scene not in self.scene_offset:
                raise KeyError(f"scene {episode.scene} was not given to this BatchedNavEnv")
            data = self.library[episode.scene]
            self.library.check_target(episode.scene, episode.target)
            local = self.library.pose_of(episode.scene, episode.start)
            self.pose[slot] = local + self.scene_offset[episode.scene]
            self.goal[slot] = self._goal_id(episode)
            self.steps[slot] = 0
            self.max_steps[slot] = self.fixed_max_steps or max_steps_for(data.room_type, self.mode)
            self.done[slot] = False
            self.target_embedding[slot] = self.targets.embedding(episode.target)
            self.target_index[slot] = self.targets.index(episode.target)
            self.parent_weights[slot] = (
                self.targets.parent_weights(data.room_type, episode.target)
                if self.rewards.pays_parent_reward(data.room_type)
                else 0.0
            )
            self.seen_parents[slot] = False
            optimal = episode.optimal_length
            if optimal < 0:
                d = int(self._distances_to_goal(episode)[local])
                optimal = d + 1 if d >= 0 else -1
            self.optimal_length[slot] = optimal
            self._distances[slot] = None if episode.target_ids else data.target_distances(episode.target)
            if self.rewards.progress_reward:
                self._progress_distances[slot] = self._distances_to_goal(episode)
            self.episodes[slot] = episode

    def _distances_to_goal(self, episode: Episode) -> np.ndarray:
        """Moves from every pose of the episode's scene to the nearest pose that sees one of its goal
        instances (the named ones if it names any)."""
        data = self.library[episode.scene]
        if not episode.target_ids:
            return data.target_distances(episode.target)
        instances = data.goal_instances(episode.target, episode.target_ids)
        return data.distances_to(data.goal_mask_for_instances(instances))

    def expert_actions(self) -> np.ndarray:
        """The shortest-path expert's action in every slot (-1 where none is known or the episode is
        over): ``Done`` where a target instance is visible, else the first movement action
        (MoveAhead, RotateLeft, RotateRight, LookUp, LookDown) that brings the agent one move
        closer to a pose that sees the target."""
        actions = np.full(self.batch_size, -1, dtype=np.int64)
        for slot in np.flatnonzero(~self.done):
            distances = self._distances[slot]
            if distances is None:
                continue
            offset = self.scene_offset[self.episodes[slot].scene]
            pose = self.pose[slot] - offset
            distance = distances[pose]
            if distance == 0:
                actions[slot] = DONE
            elif distance > 0:
                closer = distances[self.successors[self.pose[slot]] - offset] == distance - 1
                actions[slot] = int(np.argmax(closer))
        return actions

    def _progress(self, before: np.ndarray, after: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """Per slot, how many actions closer to the target the last move brought the agent (0 where
        it did not move or either pose cannot reach the target)."""
        progress = np.zeros(self.batch_size, dtype=np.float32)
        for slot in np.flatnonzero(moving & (before != after)):
            offset = self.scene_offset[self.episodes[slot].scene]
            distances = self._progress_distances[slot]
            d_before, d_after = distances[before[slot] - offset], distances[after[slot] - offset]
            if d_before >= 0 and d_after >= 0:
                progress[slot] = d_before - d_after
        return progress

    def at_goal(self) -> np.ndarray:
        keys = self.goal * self.n_poses + self.pose
        found = np.searchsorted(self._goal_keys, keys)
        found = np.minimum(found, len(self._goal_keys) - 1)
        return self._goal_keys[found] == keys if len(self._goal_keys) else np.zeros_like(keys, dtype=bool)

    def step(self, actions: np.ndarray) -> BatchStep:
        actions = np.asarray(actions, dtype=np.int64)
        active = ~self.done
        is_done = active & (actions == DONE)
        success = is_done & self.at_goal()
        moving = active & (actions != DONE)
        before = self.pose
        safe_actions = np.minimum(actions, N_MOVEMENT_ACTIONS - 1)
        after = np.where(moving, self.successors[before, safe_actions], before)
        failed = moving & (after == before)
        self.pose = after
        reward = np.where(success, self.rewards.success_reward, self.rewards.step_penalty).astype(np.float32)
        if self.rewards.parent_reward:
            seen_now = (
                self.visible_categories[after]
                if self.rewards.parent_reward_rule == "visible"
                else self.context[after, :, 0] > 0
            )
            in_view = seen_now & moving[:, None]
            bonus, self.seen_parents = parent_reward(in_view, self.parent_weights, self.seen_parents)
            reward = np.where(bonus > 0, bonus, reward).astype(np.float32)
        if self.rewards.progress_reward:
            reward += self.rewards.progress_reward * self._progress(before, after, moving)
        reward[~active] = 0.0
        self.steps += active
        truncated = active & ~is_done & (self.steps >= self.max_steps)
        self.done = self.done | is_done | truncated
        return BatchStep(reward, is_done, truncated, success, failed, active)

    @functools.cached_property
    def visible_categories(self) -> np.ndarray:
        """Bool ``[poses, C]``: the category rows with an instance visible under the success rule at
        each pose (the parent bonus's ``visible`` rule); made when first read."""
        out = np.zeros((self.n_poses, len(self.targets.categories)), dtype=bool)
        for name, data in zip(self.scene_names, self._datas, strict=True):
            poses, instances = data.visible_matrix_csr
            cats = self._category_rows(data)[instances]
            known = cats >= 0
            out[poses[known] + self.scene_offset[name], cats[known]] = True
        return out

    def _category_rows(self, data: SceneData) -> np.ndarray:
        """Int64 ``[instances]``: each of ``data``'s instances' row in the category set (-1: none)."""
        rows = self.targets.categories.type_to_index
        return np.array([rows.get(t, -1) for t in data.instance_types], dtype=np.int64)

    @functools.cached_property
    def context_distance(self) -> np.ndarray:
        """Float32 ``[poses, C]``: the distance (m, the success rule's) from each pose to the nearest
        in-view instance of each category, 0 where none is in view: what a depth reading at each
        context box would add to the context vector (``model.context_distance``); made when first read."""
        out = np.full((self.n_poses, len(self.targets.categories)), np.inf, dtype=np.float32)
        for name, data in zip(self.scene_names, self._datas, strict=True):
            cats = self._category_rows(data)[data.view_instance]
            known = cats >= 0
            poses = data.view_pose[known] + self.scene_offset[name]
            np.minimum.at(out, (poses, cats[known]), data.view_distance[known].astype(np.float32))
        out[np.isinf(out)] = 0.0
        return out

    @functools.cached_property
    def features(self) -> np.ndarray:
        """Every scene's feature maps as one pose-indexed array, made when first read: an environment
        for a model that never reads them (cvmeta, mjolnir_o, mlp) holds no second copy of the
        largest arrays of its scenes (about 24 MB for a large kitchen)."""
        return np.concatenate([d.features for d in self._datas])

    def observe(self, keys: tuple[str, ...] = OBSERVATION_KEYS) -> dict:
        """Observation arrays of the current poses, float32 (docs/guide/simulator.md, "Observations")."""
        out = {}
        for key in keys:
            if key == "context":
                out[key] = self.context[self.pose]
            elif key == "features":
                out[key] = self.features[self.pose].astype(np.float32) * self.feature_scale
            elif key == "target_embedding":
                out[key] = self.target_embedding.copy()
            elif key == "target_index":
                out[key] = self.target_index.copy()
            elif key == "context_distance":
                out[key] = self.context_distance[self.pose]
            else:
                raise KeyError(f"unknown observation key {key!r}")
        return out
