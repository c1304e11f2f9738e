"""How a run's config becomes the objects of training: scene library, targets, rewards, episode
sampler, batched environment and model (the same for every trainer)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from mapless.episodes.sampler import TrainingSampler
from mapless.knowledge import load_knowledge
from mapless.models import NavModel, build_model
from mapless.offline import offline_library
from mapless.sim.library import SceneLibrary
from mapless.sim.task import RewardConfig, TargetFields
from mapless.sim.vector import BatchedNavEnv
from mapless.train.config import TrainConfig

#: Builds the scene library in the process that needs it (async workers build their own).
LibraryFactory = Callable[[], SceneLibrary]


@dataclass(frozen=True)
class BuiltinLibrary:
    """Picklable factory of the run's scenes: the cached built-in ones, or an offline data root."""

    config: TrainConfig

    def __call__(self) -> SceneLibrary:
        env = self.config.env
        if env.offline_dir:
            return offline_library(env.offline_dir, env.sim.category_set)
        return SceneLibrary.builtin(env.sim, Path(env.cache_dir) if env.cache_dir else None)


def prepare_scenes(config: TrainConfig) -> None:
    """Build the run's missing scene caches up front, in parallel and with a progress bar."""
    BuiltinLibrary(config)().prepare(config.env.all_scenes(), progress=config.progress)


def target_fields(config: TrainConfig) -> TargetFields:
    """GloVe target embeddings and (for the parent reward) parent tables of the run's category set."""
    return TargetFields(config.model.category_set)


def reward_config(config: TrainConfig) -> RewardConfig:
    """The run's ``env.reward`` with its ``parent_reward`` None resolved for the model
    (:attr:`TrainConfig.parent_reward`)."""
    return dataclasses.replace(config.env.reward, parent_reward=config.parent_reward)


def training_sampler(config: TrainConfig, library: SceneLibrary, seed: int) -> TrainingSampler:
    env = config.env
    return TrainingSampler(
        library,
        env.scene_list(),
        env.target_set,
        seed=seed,
        variants=env.variant_map(),
        variant_fraction=env.layouts.fraction,
    )


def training_env(config: TrainConfig, library: SceneLibrary, batch_size: int) -> BatchedNavEnv:
    """``batch_size`` training episodes in lockstep on the run's scenes, targets and rewards."""
    return BatchedNavEnv(
        library,
        config.env.all_scenes(),
        batch_size,
        targets=target_fields(config),
        rewards=reward_config(config),
        mode="train",
        max_steps=config.env.max_steps,
    )


def new_model(config: TrainConfig, device: torch.device | str = "cpu") -> NavModel:
    """The run's model, its hierarchical graph with the parent edges of the run's target set."""
    model = config.model
    knowledge = load_knowledge(model.category_set, model.hierarchy_rooms, config.env.target_set)
    return build_model(model, knowledge).to(device).train()
