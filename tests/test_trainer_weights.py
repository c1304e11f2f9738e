"""Short training runs of both algorithms against recorded weights: PPO and the batched A3C
trainer, with a plain and an adaptive model each, train to the weights recorded in
tests/data/trainer_weights_golden.pt, so that a change in what an update computes (the loss, the
order of the steps, the optimizer's state, what a minibatch reads) shows up here.

Training compounds rounding over its updates, so another CPU's kernels may move the weights a
little; ``MAPLESS_GOLDEN_EXACT=1`` asks for bit-for-bit equality (on the machine that recorded).
Re-record only on purpose (a change of training): ``python tests/test_trainer_weights.py --record``."""

from __future__ import annotations

import os
import sys
from functools import cache
from pathlib import Path

import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless.train.batched import BatchedTrainer
from mapless.train.ppo import PPOTrainer

GOLDEN = Path(__file__).parent / "data" / "trainer_weights_golden.pt"
EXACT = os.environ.get("MAPLESS_GOLDEN_EXACT") == "1"
PPO = ("algo=ppo", "ppo.envs=4", "ppo.steps=8", "ppo.minibatches=2", "episodes=0", "frames=48")
CASES = {
    "ppo/a3c": (PPOTrainer, "a3c", PPO),
    "ppo/savn": (PPOTrainer, "savn", (*PPO, "model.inner_lr=0.1")),
    "ppo/mlp-imitation": (PPOTrainer, "mlp", (*PPO, "ppo.imitation_coef=0.5")),
    "batched/a3c": (BatchedTrainer, "a3c", ("model.dropout=0.25",)),
    "batched/savn": (BatchedTrainer, "savn", ("model.inner_lr=0.1",)),
}


def train(case: str) -> dict[str, torch.Tensor]:
    """The trained weights, as per-tensor fingerprints (sum, a fixed random projection, first entries)."""
    trainer_class, model, overrides = CASES[case]
    trainer = trainer_class(tiny_config(model, *overrides), None, fixture_library)
    trainer.run()
    out = {"updates": torch.tensor(trainer.counters["updates"])}
    for name, value in trainer.model.state_dict().items():
        flat = value.detach().double().flatten()
        direction = torch.randn(
            flat.numel(), generator=torch.Generator().manual_seed(len(name)), dtype=flat.dtype
        )
        out[name] = torch.cat([flat.sum().view(1), (flat * direction).sum().view(1), flat[:8]])
    return out


def record() -> None:
    torch.set_num_threads(1)
    torch.save({case: train(case) for case in CASES}, GOLDEN)


@cache
def _golden() -> dict[str, dict[str, torch.Tensor]]:
    return torch.load(GOLDEN)


@pytest.mark.parametrize("case", list(CASES))
def test_a_short_run_trains_to_the_recorded_weights(case: str, single_torch_thread) -> None:
    expected, got = _golden()[case], train(case)
    assert sorted(got) == sorted(expected)
    assert int(got.pop("updates")) == int(expected["updates"]) > 1
    for key, value in got.items():
        rtol, atol = (0.0, 0.0) if EXACT else (1e-4, 1e-6)
        torch.testing.assert_close(
            value, expected[key], rtol=rtol, atol=atol, msg=lambda m, k=key: f"{k}: {m}"
        )


if __name__ == "__main__" and "--record" in sys.argv:
    record()
