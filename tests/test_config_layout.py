"""One settings block per algorithm: the A3C settings are ``a3c:`` beside ``ppo:``, only the
chosen algorithm's block may be set (tests/test_ppo.py), and the reward settings are one
``env.reward:`` block. A key of the flat layout that preceded the blocks is refused with the place it
lives, and config files and checkpoints written in that layout still load and resume. The run
folders keep their hashes (tests/test_experiment_configs.py, test_every_shipped_run_keeps_its_folder)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.config import ConfigError, load_config, to_dict
from mapless.train.builders import reward_config
from mapless.train.config import (
    A3C_KEYS,
    LEGACY_KEYS,
    REWARD_KEYS,
    TrainConfig,
    from_legacy_layout,
    to_legacy_layout,
)
from mapless.train.recipes import load_train_config, with_recipe
from mapless.train.run import resume_config, train


@pytest.mark.parametrize(
    ("old", "value", "new"),
    [("optim.lr", 1e-3, "a3c.lr"), ("loss.gamma", 0.9, "a3c.gamma"), ("mode", "async", "a3c.mode")],
)
def test_a_key_of_the_old_layout_says_where_it_moved(
    tmp_path: Path, old: str, value: object, new: str
) -> None:
    section, _, key = old.rpartition(".")
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump({"episodes": 8, **({section: {key: value}} if section else {key: value})}))
    message = rf"config key '{old}' has moved to '{new}': the A3C settings .* are one a3c: block beside ppo:"
    with pytest.raises(ConfigError, match=message):
        load_config(TrainConfig, path)
    with pytest.raises(ConfigError, match=message):  # a --set override of the old key too
        load_train_config(None, ["episodes=8", f"{old}={value}"])


@pytest.mark.parametrize(
    ("old", "value"),
    [
        ("step_penalty", -0.1),
        ("success_reward", 10.0),
        ("parent_reward", False),
        ("parent_reward_rule", "in_frame"),
        ("progress_reward", 0.1),
        ("parent_reward_rooms", "[kitchen]"),
    ],
)
def test_a_reward_key_of_the_old_layout_says_where_it_moved(tmp_path: Path, old: str, value: object) -> None:
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump({"episodes": 8, "env": {old: value}}))
    message = (
        rf"config key 'env\.{old}' has moved to 'env\.reward\.{old}': the reward settings .* are one "
        r"env\.reward: block"
    )
    with pytest.raises(ConfigError, match=message):
        load_config(TrainConfig, path)
    with pytest.raises(ConfigError, match=message):  # a --set override of the old key too
        load_train_config(None, ["episodes=8", f"env.{old}={value}"])
    load_train_config(None, ["episodes=8", f"env.reward.{old}={value}"])  # the new key is read


def test_the_legacy_layout_holds_the_same_values() -> None:
    data = to_dict(
        tiny_config(
            "a3c",
            "a3c.lr=0.002",
            "a3c.mode=async",
            "a3c.tau=0.5",
            "env.reward.step_penalty=-0.02",
            "env.reward.parent_reward_rooms=[bedroom]",
        )
    )
    legacy = to_legacy_layout(data)
    assert "a3c" not in legacy and legacy["optim"]["lr"] == 0.002 and legacy["loss"]["tau"] == 0.5
    assert legacy["mode"] == "async" and legacy["batch_size"] == 4
    assert len(legacy["optim"]) + len(legacy["loss"]) + 3 == len(A3C_KEYS) == len(data["a3c"])
    assert "reward" not in legacy["env"] and legacy["env"]["step_penalty"] == -0.02
    assert legacy["env"]["parent_reward_rooms"] == ["bedroom"] and legacy["env"]["parent_reward"] is None
    assert len(REWARD_KEYS) == len(data["env"]["reward"])  # every reward setting moved
    assert len(LEGACY_KEYS) == len(A3C_KEYS) + len(REWARD_KEYS)
    assert from_legacy_layout(legacy) == data


def test_a_config_stored_with_the_flat_reward_keys_gives_the_same_rewards(tmp_path: Path) -> None:
    config = tiny_config(
        "cvmeta", "env.reward.parent_reward_rule=in_frame", "env.reward.parent_reward_rooms=[kitchen]"
    )
    stored = to_legacy_layout(to_dict(config))  # as a config.yaml or checkpoint of before issue 44
    assert stored["env"]["parent_reward_rule"] == "in_frame" and "reward" not in stored["env"]
    loaded = ckpt.config_of({"config": stored}, TrainConfig)
    assert loaded == config
    rewards = reward_config(loaded)
    assert rewards.parent_reward  # None resolved: cvmeta trains with the parent bonus
    assert (rewards.parent_reward_rule, rewards.parent_reward_rooms) == ("in_frame", ("kitchen",))
    assert rewards == reward_config(config)


def test_a_checkpoint_written_before_the_a3c_block_loads_and_resumes(tmp_path: Path) -> None:
    config = tiny_config("a3c", "episodes=4", "a3c.lr=0.0005")
    run = tmp_path / "run"
    train(config, run, library_factory=fixture_library)
    path = run / ckpt.CHECKPOINT_FILE
    payload = ckpt.load_file(path)  # rewritten as a file of before issue 44: old layout, no digest
    payload["config"] = to_legacy_layout(payload["config"])
    assert "optim" in payload["config"]
    torch.save(payload, path)
    assert ckpt.config_of(ckpt.load_file(path), TrainConfig) == config
    resumed, state = resume_config(run, ["episodes=8"])
    assert resumed == config.replace(episodes=8)
    stats = train(resumed, run, resume=state, library_factory=fixture_library)
    assert stats["episodes"] == 8


def test_a_recipes_block_of_the_other_algorithm_is_left_out() -> None:
    data = {"recipe": "laptop", "model": {"name": "cvmeta"}}
    assert "ppo" in with_recipe(data)  # the laptop recipe trains with PPO
    a3c = with_recipe({**data, "algo": "a3c"})
    assert "ppo" not in a3c and a3c["model"]["target_context"]  # its other keys stay
