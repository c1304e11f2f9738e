"""Navigation models: every system of the paper's comparison, selected by name (see registry)."""

from mapless.models.base import ModelConfig, ModelOutput, NavModel
from mapless.models.layers import context_vector, target_similarity
from mapless.models.registry import (
    MODELS,
    build_model,
    count_parameters,
    model_class,
    model_folder_name,
    model_names,
)

__all__ = [
    "MODELS",
    "ModelConfig",
    "ModelOutput",
    "NavModel",
    "build_model",
    "context_vector",
    "count_parameters",
    "model_class",
    "model_folder_name",
    "model_names",
    "target_similarity",
]
