"""Model registry: name -> constructor. ``build_model(ModelConfig(name=...))`` is the only entry point.

A model name (``model.name`` of every config, a checkpoint's recorded name) is one of three things:
a built-in name (:data:`MODELS`); a name an installed package registers under the ``mapless.models``
entry-point group (``[project.entry-points."mapless.models"] tiny = "mypkg.models:TinyModel"``); or
an import path ``package.module:Class`` to a :class:`NavModel` subclass, importable where mapless runs
(installed, or on ``PYTHONPATH``). A checkpoint records the name it was trained under, so a model
from one's own package is rebuilt from it as a built-in one is.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
from importlib.metadata import entry_points

from mapless.config import ConfigError
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


#: The entry-point group through which an installed package registers its models by name.
ENTRY_POINT_GROUP = "mapless.models"


def _registered() -> dict[str, object]:
    """The entry points of :data:`ENTRY_POINT_GROUP` by name (a built-in name is not replaced)."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in MODELS}


def model_names() -> list[str]:
    """The built-in models, then those installed packages register (import paths are not listed)."""
    return [*MODELS, *sorted(_registered())]


def _checked(name: str, found: object) -> type[NavModel]:
    if not (isinstance(found, type) and issubclass(found, NavModel)):
        raise ConfigError(f"model {name!r} is {found!r}, not a subclass of mapless.models.NavModel")
    return found


def _import_path(name: str) -> type[NavModel]:
    module_name, _, attribute = name.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise ConfigError(
            f"model {name!r}: cannot import {module_name!r} ({error}); install its package or put it "
            "on PYTHONPATH"
        ) from None
    try:
        found = functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        raise ConfigError(f"model {name!r}: {module_name} has no {attribute!r}") from None
    return _checked(name, found)


def model_class(name: str) -> type[NavModel]:
    """The class a model name stands for: built in, registered by an installed package, or the
    import path ``package.module:Class`` (the module docstring). Raises :class:`UnknownNameError`
    for a name that is none of these, :class:`~mapless.config.ConfigError` for an import path
    that does not lead to a :class:`NavModel` subclass."""
    if name in MODELS:
        return MODELS[name]
    if ":" in name:
        return _import_path(name)
    registered = _registered()
    if name in registered:
        return _checked(name, registered[name].load())
    summary = ", ".join(model_names()) + " (or an import path package.module:Class)"
    raise UnknownNameError("model", name, model_names(), summary)


def model_folder_name(name: str) -> str:
    """``name`` as a part of a folder name: an import path's ``:`` (which some file systems and
    TensorBoard's ``--logdir_spec`` refuse) becomes ``.``; a built-in name is unchanged."""
    return name.replace(":", ".")


def build_model(config: ModelConfig | str, knowledge: Knowledge | None = None, **overrides) -> NavModel:
    """Construct a model (any name :func:`model_class` takes). ``config`` may be a name; ``overrides``
    replace config fields.
    ``knowledge`` defaults to the packaged data of ``config.category_set``. Raises
    :class:`~mapless.models.roles.ParameterRoleError` if a trainable parameter has no role or several."""
    if isinstance(config, str):
        config = ModelConfig(name=config)
    if overrides:
        config = dataclasses.replace(config, **overrides)
    model = model_class(config.name)(config, knowledge)
    model.parameter_role_map()  # fails here, naming the parameter, rather than in a training run
    return model


def count_parameters(model: NavModel) -> tuple[int, int]:
    """``(trainable, total)``: trainable parameters, and every state-dict entry (frozen parameters and
    the frozen GloVe buffer included, as the references count them)."""
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    total = sum(t.numel() for t in model.state_dict().values())
    return trainable, total
