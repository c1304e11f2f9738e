"""The ObjectNav task's settings, read by the batched environment (which the gymnasium one
adapts): rewards, limits, and how a target is turned into observation fields."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mapless.config import ConfigError
from mapless.errors import MaplessError
from mapless.knowledge.glove import glove_vector
from mapless.knowledge.parents import parent_weights
from mapless.scenes.catalogue import ROOM_TYPES
from mapless.scenes.categories import category_set

if TYPE_CHECKING:
    from mapless.sim.scene_data import SceneData

#: SAVN's evaluation limits: 100 steps, 200 in living rooms; training episodes stop at 30.
TRAIN_MAX_STEPS = 30
EVAL_MAX_STEPS = {"kitchen": 100, "living_room": 200, "bedroom": 100, "bathroom": 100}


#: What makes a parent object count as seen for the parent bonus (:class:`RewardConfig`).
PARENT_REWARD_RULES = ("visible", "in_frame")


@dataclass(frozen=True)
class RewardConfig:
    """SAVN's rewards: ``step_penalty`` per step; ``success_reward`` replaces it on a successful
    ``Done``. With ``parent_reward`` on, the first time in an episode a parent object of the target
    comes into view, its bonus replaces the step penalty (MJOLNIR's hierarchical reward, with the
    seen set reset at every episode start). ``parent_reward_rule`` says what "into view" means:
    ``visible``, the success rule's visibility (MJOLNIR reads THOR's ``visible`` flag, which is this
    rule at its 1.5 m), or ``in_frame``, any instance in the frame at any distance (this project's
    rule before 2026-12-06). ``progress_reward`` (0 = off, as in the references) adds,
    at every move, that weight times the decrease of the shortest-path distance (in actions) to the
    nearest pose that sees the target: AllenAct's geodesic-progress shaping in this pose graph's unit.
    It is potential-based, so it telescopes to ``weight * (d_start - d_end)`` over an episode and leaves
    the optimal policy unchanged.

    A training run's ``env.reward`` block (:class:`mapless.train.config.EnvConfig`). There
    ``parent_reward`` None (the default) leaves the bonus to the model: on for mjolnir_o/mjolnir_r
    (MJOLNIR's ``--partial_reward``) and cvmeta (the paper's hierarchical training signal), off
    otherwise (:attr:`mapless.train.config.TrainConfig.parent_reward` resolves it before the
    environment is built); an environment given None pays no bonus."""

    step_penalty: float = -0.01
    success_reward: float = 5.0
    parent_reward: bool | None = None
    parent_reward_rule: str = "visible"
    progress_reward: float = 0.0
    #: Room types whose parents pay the bonus (the hierarchy ablation drops one room type).
    parent_reward_rooms: tuple[str, ...] = ROOM_TYPES

    def __post_init__(self) -> None:
        for key in ("step_penalty", "success_reward", "progress_reward"):
            value = getattr(self, key)
            if not math.isfinite(value):
                raise ConfigError(f"config key 'env.reward.{key}': must be finite, got {value}")
        if self.progress_reward < 0:
            raise ConfigError(
                f"config key 'env.reward.progress_reward': must be >= 0, got {self.progress_reward}"
            )
        if self.parent_reward_rule not in PARENT_REWARD_RULES:
            raise ConfigError(
                f"config key 'env.reward.parent_reward_rule': {self.parent_reward_rule!r} is not one of {PARENT_REWARD_RULES}"
            )
        if unknown := set(self.parent_reward_rooms) - set(ROOM_TYPES):
            raise ConfigError(
                f"config key 'env.reward.parent_reward_rooms': unknown room types {sorted(unknown)}; "
                f"valid: {ROOM_TYPES}"
            )

    def pays_parent_reward(self, room_type: str) -> bool:
        return bool(self.parent_reward) and room_type in self.parent_reward_rooms


def max_steps_for(room_type: str, mode: str) -> int:
    return TRAIN_MAX_STEPS if mode == "train" else EVAL_MAX_STEPS[room_type]


class TargetFields:
    """Per-target observation fields (GloVe vector, category row) and per (room, target) the parent
    weights over categories, cached."""

    def __init__(self, category_set_name: str = "mjolnir101"):
        self.categories = category_set(category_set_name)
        self.category_set_name = category_set_name
        self._embeddings: dict[str, np.ndarray] = {}
        self._parents: dict[tuple[str, str], np.ndarray] = {}

    def embedding(self, target: str) -> np.ndarray:
        if target not in self._embeddings:
            self._embeddings[target] = np.asarray(
                glove_vector(target, self.category_set_name), dtype=np.float32
            )
        return self._embeddings[target]

    def index(self, target: str) -> int:
        return self.categories.type_to_index.get(target, -1)

    def parent_weights(self, room_type: str, target: str) -> np.ndarray:
        """``[C]`` parent bonus per category row (0 for non-parents)."""
        key = (room_type, target)
        if key not in self._parents:
            self._parents[key] = parent_weights(room_type, target, self.category_set_name)
        return self._parents[key]


def resolve_target_fields(targets: TargetFields | None, category_set: str | None) -> TargetFields:
    """The environments' target fields: ``targets`` if given, else those of ``category_set``
    (default ``mjolnir101``). Both given and naming different sets is an error: the observation's
    category rows would silently follow one and the caller expect the other."""
    if targets is None:
        return TargetFields(category_set or "mjolnir101")
    if category_set is not None and category_set != targets.category_set_name:
        raise MaplessError(
            f"category_set {category_set!r} differs from the given targets' "
            f"{targets.category_set_name!r}; pass one of them"
        )
    return targets


def check_scene_categories(data: SceneData, targets: TargetFields) -> None:
    """A scene whose context rows are not the targets' category set is refused by name."""
    rows, expected = data.context.shape[1], len(targets.categories)
    if rows != expected:
        raise MaplessError(
            f"scene {data.scene} has {rows} category rows, the {targets.category_set_name!r} "
            f"category set {expected}: the scenes were built for another category set "
            "(sim.category_set)"
        )
