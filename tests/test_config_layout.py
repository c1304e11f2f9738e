"""One settings block per algorithm: the A3C settings are ``a3c:`` beside ``ppo:``, only the
chosen algorithm's block may be set (tests/test_ppo.py), so ``a3c.precision`` is refused under PPO,
and PPO's meta-learning keys (``ppo.meta``) are refused for a model that does not meta-learn, saying
where they are read; the reward settings are one ``env.reward:`` block; a key of an earlier layout is refused
naming where it lives now, and a stored config of an earlier layout reads as today's."""

from __future__ import annotations

import pytest

from mapless.config import ConfigError, move_keys, to_dict
from mapless.experiments import load_experiment
from mapless.train.config import LAYOUT_CHANGES, in_current_layout, stored_train_config
from mapless.train.recipes import load_train_config, with_recipe


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("ppo.meta.navigation_loss", "after_interaction"),
        ("ppo.meta.learned_loss_from_imitation", True),
        ("ppo.meta.train_learned_loss", False),
    ],
)
def test_ppos_meta_learning_keys_are_refused_where_they_would_be_ignored(key: str, value: object) -> None:
    base = ["episodes=8", f"{key}={value}"]
    with pytest.raises(
        ConfigError, match=r"config key 'ppo.meta': algo is a3c, which reads only the a3c: block"
    ):
        load_train_config(None, [*base, "model.name=cvmeta"])
    where = (
        r"ppo.meta is read for an adaptive model \(savn, gve, spatt, cvmeta\) whose model.adapt is not none"
    )
    with pytest.raises(
        ConfigError, match=rf"config key '{key}': model 'a3c' .* does not meta-learn, .*; {where}"
    ):
        load_train_config(None, [*base, "algo=ppo", "model.name=a3c"])
    with pytest.raises(ConfigError, match=r"model 'cvmeta' \(model.adapt none\) does not meta-learn"):
        load_train_config(None, [*base, "algo=ppo", "model.name=cvmeta", "model.adapt=none"])
    config = load_train_config(None, [*base, "algo=ppo", "model.name=cvmeta"])
    assert getattr(config.ppo.meta, key.rsplit(".", 1)[1]) == value
    # first_order is read by both algorithms' meta-learning.
    assert load_train_config(
        None, ["episodes=8", "meta.first_order=true", "model.name=savn"]
    ).meta.first_order


def test_a_key_of_an_earlier_layout_is_refused_naming_where_it_lives_now() -> None:
    with pytest.raises(
        ConfigError, match=r"config key 'meta.navigation_loss' is now 'ppo.meta.navigation_loss'"
    ):
        load_train_config(None, ["episodes=8", "algo=ppo", "meta.navigation_loss=after_interaction"])
    with pytest.raises(ConfigError, match=r"config key 'optim.lr' is now 'a3c.lr'"):
        load_train_config(None, ["episodes=8", "optim.lr=0.001"])
    with pytest.raises(ConfigError, match=r"config key 'precision' is now 'a3c.precision'"):
        load_train_config(None, ["episodes=8", "precision=bf16"])
    with pytest.raises(ConfigError, match=r"config key 'env.step_penalty' is now 'env.reward.step_penalty'"):
        load_train_config(None, ["episodes=8", "env.step_penalty=-0.1"])
    with pytest.raises(
        ConfigError, match=r"config key 'meta.train_learned_loss' is now 'ppo.meta.train_learned_loss'"
    ):
        load_experiment("ablation", "smoke", overrides=["train.meta.train_learned_loss=false"])


def test_a_stored_config_of_an_earlier_layout_reads_as_todays() -> None:
    """A checkpoint's or config.yaml's config written before a layout change (the resume, the zoo's
    files and ``mapless runs migrate`` read them) types to the config it was written from."""
    today = load_train_config(
        None,
        ["episodes=8", "algo=ppo", "model.name=cvmeta", "ppo.meta.navigation_loss=after_interaction",
         "ppo.meta.train_learned_loss=false", "env.reward.step_penalty=-0.02", "ppo.lr=0.001"],
    )  # fmt: skip
    data = to_dict(today)
    assert in_current_layout(data) == data
    for change in range(len(LAYOUT_CHANGES)):
        earlier = data
        for _, moves in reversed(LAYOUT_CHANGES[change:]):
            earlier = move_keys(earlier, [(new, old) for old, new in moves])
        assert earlier != data and stored_train_config(earlier) == today
    before_ppo_meta = move_keys(data, [(new, old) for _, moves in LAYOUT_CHANGES[1:] for old, new in moves])
    assert before_ppo_meta["meta"] == {
        "first_order": False, "navigation_loss": "after_interaction",
        "learned_loss_from_imitation": False, "train_learned_loss": False,
    }  # fmt: skip
    assert "meta" not in before_ppo_meta["ppo"]
    assert before_ppo_meta["precision"] == "fp32" and "precision" not in before_ppo_meta["a3c"]


def test_precision_is_read_by_a3c_only() -> None:
    assert load_train_config(None, ["episodes=8", "a3c.precision=bf16"]).a3c.precision == "bf16"
    with pytest.raises(
        ConfigError, match=r"config key 'a3c.precision': algo is ppo, which reads only the ppo: block"
    ):
        load_train_config(None, ["episodes=8", "a3c.precision=bf16", "algo=ppo"])


def test_a_recipes_block_of_the_other_algorithm_is_left_out() -> None:
    data = {"recipe": "laptop", "model": {"name": "cvmeta"}}
    assert "ppo" in with_recipe(data)  # the laptop recipe trains with PPO
    a3c = with_recipe({**data, "algo": "a3c"})
    assert "ppo" not in a3c and a3c["model"]["target_context"]  # its other keys stay
