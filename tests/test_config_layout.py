"""One settings block per algorithm: the A3C settings are ``a3c:`` beside ``ppo:``, only the
chosen algorithm's block may be set (tests/test_ppo.py), a meta-learning key only PPO reads or
``precision``, which only A3C reads, is refused where the run would ignore it, saying where it
belongs, and the reward settings are one ``env.reward:`` block."""

from __future__ import annotations

import pytest

from mapless.config import ConfigError
from mapless.train.recipes import load_train_config, with_recipe


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("meta.navigation_loss", "after_interaction"),
        ("meta.learned_loss_from_imitation", True),
        ("meta.train_learned_loss", False),
    ],
)
def test_a_meta_key_only_ppo_reads_is_refused_where_it_would_be_ignored(key: str, value: object) -> None:
    where = r"it belongs to the PPO trainer's meta-learning: algo: ppo with an adaptive model"
    base = ["episodes=8", f"{key}={value}"]
    with pytest.raises(ConfigError, match=rf"config key '{key}': algo is a3c, which ignores it; {where}"):
        load_train_config(None, [*base, "model.name=cvmeta"])
    with pytest.raises(ConfigError, match=rf"config key '{key}': model 'a3c' .* does not meta-learn"):
        load_train_config(None, [*base, "algo=ppo", "model.name=a3c"])
    with pytest.raises(ConfigError, match=r"model 'cvmeta' \(model.adapt none\) does not meta-learn"):
        load_train_config(None, [*base, "algo=ppo", "model.name=cvmeta", "model.adapt=none"])
    config = load_train_config(None, [*base, "algo=ppo", "model.name=cvmeta"])
    assert getattr(config.meta, key.split(".")[1]) == value
    # first_order is read by both algorithms' meta-learning.
    assert load_train_config(
        None, ["episodes=8", "meta.first_order=true", "model.name=savn"]
    ).meta.first_order


def test_precision_is_read_by_a3c_only() -> None:
    assert load_train_config(None, ["episodes=8", "precision=bf16"]).precision == "bf16"
    with pytest.raises(
        ConfigError, match="config key 'precision': bf16 is implemented for the A3C trainers only"
    ):
        load_train_config(None, ["episodes=8", "precision=bf16", "algo=ppo"])


def test_a_key_of_the_layout_before_the_blocks_is_unknown() -> None:
    # The layout of before the a3c: and env.reward: blocks is read only by mapless runs migrate.
    with pytest.raises(ConfigError, match="unknown config key 'optim'"):
        load_train_config(None, ["episodes=8", "optim.lr=0.001"])
    with pytest.raises(ConfigError, match=r"unknown config key 'env\.step_penalty'"):
        load_train_config(None, ["episodes=8", "env.step_penalty=-0.1"])


def test_a_recipes_block_of_the_other_algorithm_is_left_out() -> None:
    data = {"recipe": "laptop", "model": {"name": "cvmeta"}}
    assert "ppo" in with_recipe(data)  # the laptop recipe trains with PPO
    a3c = with_recipe({**data, "algo": "a3c"})
    assert "ppo" not in a3c and a3c["model"]["target_context"]  # its other keys stay
