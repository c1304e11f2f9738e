"""No setting without effect: every registered model against every model-specific config key.

Each model declares the ModelConfig keys it reads (``NavModel.settings``, mapless.models.settings).
The walk builds every model with every key changed, under the default settings and under the
opposite of every condition a declaration can have (the target row on, the other graph, no
meta-learning): a key the model is declared to read must change the built model (its parameters,
its outputs or its inner loop), and a key it does not read must leave its outputs alone and be
refused by the training config, with a message naming exactly the models that read it.
"""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from mapless.checkpoint import digest
from mapless.config import ConfigError, from_dict
from mapless.models import MODELS, ModelConfig, build_model
from mapless.models.settings import reads, resolved, unread_setting
from mapless.models.synthetic import synthetic_observations
from mapless.train.config import TrainConfig

HIDDEN = 32
#: Two values per key, each away from the default: the walk takes the first that changes the base.
CHANGES = {
    "category_set": ("all_types", "mjolnir101"),
    "feature_channels": (200, 300),
    "hidden_size": (48, 64),
    "dropout": (0.5, 0.1),
    "graph": ("hierarchical", "vg"),
    "hierarchy_rooms": (("kitchen",), ("bedroom",)),
    "inner_lr": (0.5, 0.25),
    "interaction_steps": (3, 4),
    "max_inner_updates": (2, 1),
    "fusion_channels": (8, 16),
    "gcn_hidden": (16, 24),
    "reference_extras": (True, False),
    "adapt": ("none", "all"),
    "target_context": (True, False),
    "semantic_map": (True, False),
    "context_distance": (True, False),
}
#: The opposite of each declaration condition's default.
FLIPS = {"target_context": True, "graph": "hierarchical", "adapt": "none"}


def test_the_walk_covers_every_model_specific_key():
    keys = {f.name for f in dataclasses.fields(ModelConfig)} - {"name"}
    assert set(CHANGES) == keys
    declared = {key for model in MODELS.values() for key in model.settings}
    assert declared == keys  # a key no model reads would be a setting without effect for all


def _bases(name: str) -> list[ModelConfig]:
    model = MODELS[name]
    default = ModelConfig(name=name, hidden_size=HIDDEN if "hidden_size" in model.settings else 512)
    flips = {}
    for key, value in FLIPS.items():
        if key == "graph" and model.default_graph == value:
            value = "vg"
        if reads(model, default, key):
            flips[key] = value
    return [default, dataclasses.replace(default, **flips)] if flips else [default]


def _fingerprint(config: ModelConfig) -> tuple:
    """(parameter names and shapes, the weights, one step's outputs in training mode, the inner loop's
    settings): what a setting can change of a built model."""
    torch.manual_seed(0)
    model = build_model(config).train()
    generator = torch.Generator().manual_seed(0)
    obs = synthetic_observations(3, model.knowledge, model.feature_channels, generator)
    hidden = tuple(torch.randn(3, model.hidden_size, generator=generator) for _ in range(2))
    torch.manual_seed(1)
    out = model(obs, hidden, torch.full((3, 6), 1 / 6))
    inner = None
    if model.adaptive:
        inner = (model.adapts_policy_only, model.inner_lr, config.interaction_steps, config.max_inner_updates)
    layout = [(k, tuple(v.shape)) for k, v in model.state_dict().items()]
    return layout, digest(model.state_dict()), digest([out.logits, out.value]), inner


def _change(base: ModelConfig, key: str) -> ModelConfig:
    value = next(v for v in CHANGES[key] if v != resolved(MODELS[base.name], base, key))
    return dataclasses.replace(base, **{key: value})


def _readers(key: str) -> set[str]:
    return {name for name, model in MODELS.items() if key in model.settings}


@pytest.mark.parametrize("name", list(MODELS))
def test_a_model_reads_the_keys_it_declares_and_refuses_the_others(name):
    model = MODELS[name]
    for base in _bases(name):
        assert unread_setting(MODELS, base) is None
        before = _fingerprint(base)
        for key in CHANGES:
            changed = _change(base, key)
            after = _fingerprint(changed)
            if reads(model, changed, key):
                assert after != before, f"{name} is declared to read model.{key} but ignores it ({base})"
                continue
            # Not read: the model acts the same, and the setting is refused.
            assert after[2:] == before[2:], f"{name} is declared not to read model.{key} but uses it"
            problem = unread_setting(MODELS, changed)
            assert problem is not None and problem.startswith(f"config key 'model.{key}'"), (name, key)
            named = set(re.findall(r"\b(\w+)(?: \(with [^)]*\))?(?:, |\. )", problem.split("read it: ")[1]))
            assert named == _readers(key), (name, key, problem)
            if name != "random":  # the training config refuses the random agent first
                data = {"episodes": 1, "model": dataclasses.asdict(changed)}
                with pytest.raises(ConfigError, match=re.escape(problem)):
                    from_dict(TrainConfig, data)


def test_context_distance_on_a_model_that_never_reads_it_is_refused_naming_its_readers():
    for name, extra in (("mlp", {}), ("mjolnir_o", {"target_context": True}), ("a3c", {})):
        with pytest.raises(ConfigError) as error:
            from_dict(
                TrainConfig, {"episodes": 1, "model": {"name": name, "context_distance": True, **extra}}
            )
        message = str(error.value)
        assert "'model.context_distance'" in message and "cvmeta" in message
        assert "a3c (with model.target_context)" in message
    # Where it is read, it is accepted.
    config = from_dict(
        TrainConfig,
        {"episodes": 1, "model": {"name": "a3c", "target_context": True, "context_distance": True}},
    )
    assert config.model.context_distance


def test_a_key_left_at_its_default_is_not_refused():
    config = from_dict(
        TrainConfig, {"episodes": 1, "model": {"name": "mlp", "context_distance": False, "graph": None}}
    )
    assert config.model.name == "mlp"
