"""The recipe of docs/guide/models.md, "Adding a model": a minimal model registered by name trains for one
PPO update and is evaluated, through the same code as every shipped model."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from train_fixtures import fixture_library, tiny_config

from mapless.agent.evaluation import ModelAgent
from mapless.evaluate.runner import EvalSettings, run_episodes
from mapless.models import registry
from mapless.models.base import NUM_ACTIONS, RECURRENT_CORE_ROLES, RecurrentNavModel
from mapless.models.layers import target_row
from mapless.models.roles import ParameterRoles
from mapless.train.ppo import PPOTrainer


class TargetRowModel(RecurrentNavModel):
    """Reads only the target's own context row and the previous policy."""

    description = "example: the target's context row -> LSTM"
    parameter_roles = RECURRENT_CORE_ROLES | ParameterRoles(policy=("embed",))

    def __init__(self, config, knowledge=None):
        super().__init__(config, knowledge)
        self.embed = nn.Linear(4 + NUM_ACTIONS, 32)
        self.build_recurrent_core(32, glorot=False)

    def encode(self, obs: dict[str, Tensor], hidden, prev_policy: Tensor):
        row = target_row(obs["context"], obs["target_index"])
        return F.relu(self.embed(torch.cat([row, prev_policy], dim=1))), None


def test_a_new_model_registers_trains_and_evaluates(monkeypatch) -> None:
    monkeypatch.setitem(registry.MODELS, "target_row", TargetRowModel)
    config = tiny_config(
        "target_row", "algo=ppo", "ppo.envs=4", "ppo.minibatches=2", "episodes=0", "frames=64"
    )
    trainer = PPOTrainer(config, None, fixture_library)
    trainer.build()
    assert trainer.obs_keys == ("context", "target_index")  # found by probing what the model reads
    before = [p.detach().clone() for p in trainer.params]
    trainer.update()
    assert any(not torch.equal(a, b) for a, b in zip(before, trainer.params, strict=True))

    sampler_rng = np.random.default_rng(0)
    episodes = [trainer.sampler.sample(sampler_rng) for _ in range(6)]
    agent = ModelAgent(trainer.model, batch_size=3)
    results = run_episodes(
        agent, fixture_library(), episodes, list(range(6)), EvalSettings(batch_size=3, workers=1)
    )
    assert len(results) == 6 and all(r.length >= 1 for r in results)
