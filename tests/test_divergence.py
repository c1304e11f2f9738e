"""One divergence rule for every trainer (mapless/train/gradients.py ``check_finite``): batched A3C,
PPO and Hogwild stop at a NaN or infinite gradient before the optimizer step, the checkpoint on disk
stays the last good state, and the message never promises a checkpoint that the run did not write.
torchrun ranks: tests/test_train_distributed.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.errors import TrainingDiverged
from mapless.train.gradients import check_finite
from mapless.train.run import resume_config, train

#: A finite but absurd penalty: the value loss overflows to inf and the gradient to NaN.
DIVERGING = "env.reward.step_penalty=-1e38"
TRAINERS = {
    "batched": (),
    "ppo": ("algo=ppo", "ppo.envs=4", "ppo.minibatches=2", "episodes=0", "frames=400"),
    "async": ("a3c.mode=async", "a3c.workers=2"),
}
#: Hogwild starts worker processes: the slow tier.
TRAINER_CASES = [pytest.param(t, marks=pytest.mark.slow) if t == "async" else t for t in TRAINERS]


def test_the_rule() -> None:
    counters = {"updates": 4, "episodes": 32, "frames": 300}
    check_finite(12.5, counters, None)  # a finite norm passes, whatever was saved
    for norm in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(TrainingDiverged, match=r"update 5 \(32 episodes, 300 frames\)") as saved:
            check_finite(norm, counters, {"episodes": 16})
        assert "checkpoint.pt still holds the last good state, at 16 episodes" in str(saved.value)
        with pytest.raises(TrainingDiverged, match="before the run wrote its first checkpoint") as none:
            check_finite(norm, counters, None)
        assert "checkpoint.pt" not in str(none.value)


@pytest.mark.parametrize("trainer", TRAINER_CASES)
def test_a_diverging_run_stops_with_a_clear_error_and_keeps_its_last_checkpoint(
    tmp_path: Path, trainer: str
) -> None:
    run = tmp_path / "run"
    train(tiny_config("a3c", *TRAINERS[trainer], "checkpoint_every=1"), run, library_factory=fixture_library)
    before = ckpt.load_file(run / ckpt.CHECKPOINT_FILE)
    config, state = resume_config(run, [DIVERGING, "frames=100000", "episodes=0"])
    with pytest.raises(TrainingDiverged, match=r"checkpoint\.pt still holds the last good state") as error:
        train(config, run, resume=state, library_factory=fixture_library)
    after = ckpt.load_file(run / ckpt.CHECKPOINT_FILE)
    assert f"at {after['counters']['episodes']} episodes" in str(error.value)
    assert all(torch.isfinite(value).all() for value in after["model"].values())
    if trainer != "async":  # Hogwild workers may finish an episode of finite gradient first
        assert after["counters"] == before["counters"]
        for key, value in before["model"].items():
            assert torch.equal(value, after["model"][key]), key


@pytest.mark.parametrize("trainer", TRAINER_CASES)
def test_divergence_before_the_first_checkpoint_promises_none(tmp_path: Path, trainer: str) -> None:
    run = tmp_path / "run"
    config = tiny_config("a3c", *TRAINERS[trainer], DIVERGING, "checkpoint_every=1000")
    with pytest.raises(TrainingDiverged, match="before the run wrote its first checkpoint") as error:
        train(config, run, library_factory=fixture_library)
    assert "still holds" not in str(error.value)
    assert not (run / ckpt.CHECKPOINT_FILE).exists() and not ckpt.snapshots(run)
