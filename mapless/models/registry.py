"""Model registry: name -> constructor. ``build_model(ModelConfig(name=...))`` is the only entry point."""

from __future__ import annotations

import dataclasses

from mapless.errors import UnknownNameError
from mapless.knowledge import Knowledge
from mapless.models.a3c import A3CModel, SavnModel
from mapless.models.base import ModelConfig, NavModel
from mapless.models.cvmeta import ContextVectorMetaModel
from mapless.models.graph_models import GveModel, ScenePriorsModel
from mapless.models.mjolnir import MjolnirObjectModel, MjolnirResnetModel
from mapless.models.mlp import MlpModel
from mapless.models.spatt import SpattModel
from mapless.models.uniform import RandomModel

MODELS: dict[str, type[NavModel]] = {
    "random": RandomModel,
    "a3c": A3CModel,
    "sp": ScenePriorsModel,
    "savn": SavnModel,
    "gve": GveModel,
    "spatt": SpattModel,
    "mjolnir_o": MjolnirObjectModel,
    "mjolnir_r": MjolnirResnetModel,
    "cvmeta": ContextVectorMetaModel,
    "mlp": MlpModel,
}


def model_names() -> list[str]:
    return list(MODELS)


def build_model(config: ModelConfig | str, knowledge: Knowledge | None = None, **overrides) -> NavModel:
    """Construct a registered model. ``config`` may be a name; ``overrides`` replace config fields.
    ``knowledge`` defaults to the packaged data of ``config.category_set``. Raises
    :class:`~mapless.models.roles.ParameterRoleError` if a trainable parameter has no role or several."""
    if isinstance(config, str):
        config = ModelConfig(name=config)
    if overrides:
        config = dataclasses.replace(config, **overrides)
    if config.name not in MODELS:
        raise UnknownNameError("model", config.name, MODELS)
    model = MODELS[config.name](config, knowledge)
    model.parameter_role_map()  # fails here, naming the parameter, rather than in a training run
    return model


def count_parameters(model: NavModel) -> tuple[int, int]:
    """``(trainable, total)``: trainable parameters, and every state-dict entry (frozen parameters and
    the frozen GloVe buffer included, as the references count them)."""
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    total = sum(t.numel() for t in model.state_dict().values())
    return trainable, total
