"""The recipe of docs/guide/models.md, "Adding a model": the guide's module, written as it stands into
a package outside the repository and named by its import path, trains for one PPO update and is
evaluated, through the same code as every shipped model."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless.agent.evaluation import ModelAgent
from mapless.evaluate.runner import EvalSettings, run_episodes
from mapless.models import model_class
from mapless.train.ppo import PPOTrainer

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide" / "models.md"


def guide_module() -> str:
    """The first Python block of the guide's "Adding a model" section."""
    section = GUIDE.read_text().split("## Adding a model", 1)[1].split("\n## ", 1)[0]
    (first, *_) = re.findall(r"```python\n(.*?)```", section, re.DOTALL)
    return first


@pytest.fixture
def guide_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text("")
    (tmp_path / "mypkg" / "models.py").write_text(guide_module())
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "mypkg.models:TargetRowModel"
    for name in [m for m in sys.modules if m == "mypkg" or m.startswith("mypkg.")]:
        del sys.modules[name]


def test_the_guides_model_from_its_own_package_trains_and_evaluates(guide_package: str) -> None:
    assert model_class(guide_package).__module__ == "mypkg.models"
    config = tiny_config(
        guide_package, "algo=ppo", "ppo.envs=4", "ppo.minibatches=2", "episodes=0", "frames=64"
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
