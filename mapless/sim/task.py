"""The ObjectNav task rules shared by the single and the batched environment: rewards, limits,
and how a target is turned into observation fields."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from mapless.scenes.categories import category_set
from mapless.sim.scene_data import SceneData

#: SAVN's evaluation limits: 100 steps, 200 in living rooms; training episodes stop at 30.
TRAIN_MAX_STEPS = 30
EVAL_MAX_STEPS = {"kitchen": 100, "living_room": 200, "bedroom": 100, "bathroom": 100}


@dataclass(frozen=True)
class RewardConfig:
    """SAVN's rewards: ``step_penalty`` per step; ``success_reward`` replaces it on a successful
    ``Done``. With ``parent_reward`` on, the first time in an episode a parent object of the target
    comes into view, its bonus replaces the step penalty (MJOLNIR's hierarchical reward, with the
    seen set reset at every episode start)."""

    step_penalty: float = -0.01
    success_reward: float = 5.0
    parent_reward: bool = False


def max_steps_for(room_type: str, mode: str) -> int:
    return TRAIN_MAX_STEPS if mode == "train" else EVAL_MAX_STEPS[room_type]


#: ``(room_type, target) -> {parent object type: bonus}``; provided by the knowledge module.
ParentTable = Callable[[str, str], Mapping[str, float]]
#: ``target type -> 300-d embedding``.
TargetEmbedder = Callable[[str], np.ndarray]


def zero_embedder(target: str) -> np.ndarray:
    return np.zeros(300, dtype=np.float32)


class TargetFields:
    """Caches per target the observation fields and per (room, target) the parent bonus vector
    over categories."""

    def __init__(self, category_set_name: str, embedder: TargetEmbedder | None = None,
                 parent_table: ParentTable | None = None):
        self.categories = category_set(category_set_name)
        self._embedder = embedder or zero_embedder
        self._parent_table = parent_table
        self._embeddings: dict[str, np.ndarray] = {}
        self._parents: dict[tuple[str, str], np.ndarray] = {}

    def embedding(self, target: str) -> np.ndarray:
        if target not in self._embeddings:
            self._embeddings[target] = np.asarray(self._embedder(target), dtype=np.float32)
        return self._embeddings[target]

    def index(self, target: str) -> int:
        return self.categories.type_to_index.get(target, -1)

    def parent_bonus(self, room_type: str, target: str) -> np.ndarray:
        """``[C]`` bonus per category (0 for non-parents)."""
        key = (room_type, target)
        if key not in self._parents:
            bonus = np.zeros(len(self.categories), dtype=np.float32)
            if self._parent_table is not None:
                for parent, value in self._parent_table(room_type, target).items():
                    index = self.categories.type_to_index.get(parent)
                    if index is not None:
                        bonus[index] = max(bonus[index], value)
            self._parents[key] = bonus
        return self._parents[key]


def in_view_categories(data: SceneData, pose: int) -> np.ndarray:
    return data.context[pose, :, 0] > 0
