"""Which model settings each model reads, so that a setting a model never reads is an error rather
than a claim its run folder makes about an input the model never saw.

Every model class declares, as :attr:`NavModel.settings <mapless.models.base.NavModel>`, the
:class:`~mapless.models.ModelConfig` keys it reads, each with the condition under which it does:
``""`` (always), ``"target_context"`` (while that switch is on), ``"graph=hierarchical"`` (while the
resolved key has that value) or ``"adapt!=none"`` (while it has another). ``model.name`` is read by
every model and declared by none. A key set to its default claims nothing and is never refused.
``tests/test_model_settings.py`` builds every model with every key changed and checks that the
declarations match what the built model does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

#: The keys every recurrent model reads (the random agent reads none).
RECURRENT = {"category_set": "", "feature_channels": "", "hidden_size": ""}
#: SAVN's embedding (a3c, savn, sp, gve, mjolnir_r): dropout, and the target's context row.
SAVN_EMBEDDING = {
    "dropout": "",
    "target_context": "",
    "context_distance": "target_context",
    "reference_extras": "",
}
#: Models with a category graph: which graph, and the hierarchical graph's rooms.
GRAPH = {"graph": "", "hierarchy_rooms": "graph=hierarchical"}
#: Adaptive models: what the inner loop adapts, and its settings while it runs at all.
ADAPTIVE = {
    "adapt": "",
    "inner_lr": "adapt!=none",
    "interaction_steps": "adapt!=none",
    "max_inner_updates": "adapt!=none",
    "reference_extras": "",
}


def resolved(model_class: type, config: Any, key: str) -> Any:
    """``config``'s value of ``key`` as ``model_class`` reads it (None resolved to its default)."""
    value = getattr(config, key)
    if value is None and key in ("graph", "adapt"):
        return getattr(model_class, f"default_{key}")
    return value


def holds(model_class: type, config: Any, condition: str) -> bool:
    """Whether a declaration's condition holds for ``config`` (the module docstring's forms)."""
    if not condition:
        return True
    if "!=" in condition:
        key, value = condition.split("!=", 1)
        return str(resolved(model_class, config, key)) != value
    if "=" in condition:
        key, value = condition.split("=", 1)
        return str(resolved(model_class, config, key)) == value
    return bool(resolved(model_class, config, condition))


def reads(model_class: type, config: Any, key: str) -> bool:
    """Whether ``model_class`` reads ``key`` of ``config``."""
    declared = getattr(model_class, "settings", {})
    return key in declared and holds(model_class, config, declared[key])


def readers(models: Mapping[str, type], key: str) -> str:
    """The models that read ``key``, each with its condition: ``a3c (with model.target_context), cvmeta``."""
    named = []
    for name, model_class in models.items():
        condition = getattr(model_class, "settings", {}).get(key)
        if condition is not None:
            named.append(f"{name} (with model.{condition})" if condition else name)
    return ", ".join(named) or "none"


def unread_setting(models: Mapping[str, type], config: Any) -> str | None:
    """Why a setting of ``config`` (a ModelConfig) has no effect on its model, or None: the first key
    set away from its default that the model does not read, with the models that do read it."""
    model_class = models[config.name]
    default = type(config)()
    for field in dataclasses.fields(config):
        key = field.name
        if key == "name" or getattr(config, key) == getattr(default, key):
            continue
        if not reads(model_class, config, key):
            condition = getattr(model_class, "settings", {}).get(key)
            why = (
                f"{config.name} reads it only with model.{condition}"
                if condition
                else f"{config.name} does not read it"
            )
            return (
                f"config key 'model.{key}': {getattr(config, key)!r} would have no effect: {why}; "
                f"the models that read it: {readers(models, key)}. Leave it at its default "
                f"({getattr(default, key)!r}) or choose one of those models"
            )
    return None
