"""mapless: object-goal visual mapless navigation in the 120 real iTHOR floor plans.

Data flows one way: ``scenes`` (layouts) -> ``sim`` (pose graph, per-pose observations,
environments) -> ``models`` (agents) -> ``train`` / ``evaluate`` -> reports.

``import mapless`` registers the gymnasium environment ``mapless/ObjectNav-v0`` and offers the names
a notebook needs (docs/guide/tutorial.md), each imported on first use, so that the import itself
stays cheap (no torch) for the command line:

* an environment: :func:`make_env`, :func:`make_vec_env`, :class:`ObjectNavEnv`, :class:`Episode`,
  :func:`fixed_episodes` (the shipped evaluation sets), :func:`scene_library`;
* a model: :func:`build_model`, :func:`model_names`, :func:`load_model` (a trained one);
* training: :func:`load_train_config` (a :class:`TrainConfig` from ``key=value`` settings),
  :func:`train_model` (``mapless.train.run.train``);
* evaluation: :func:`evaluate_agent` (``mapless.evaluate.runner.evaluate``) with an
  :class:`AgentSpec` and :class:`EvalSettings`, :func:`summarize`;
* comparison: :func:`comparison_table` (paired over the same episodes), :func:`read_results`;
* pictures: :func:`trajectory_figure`, :func:`trajectory_gif`.
"""

import importlib

import gymnasium

__version__ = "0.1.0"
ENV_ID = "mapless/ObjectNav-v0"

#: The public names and the modules that define them. Each module is imported when its name is first
#: read: a static import here would load torch with every ``import mapless`` (and would import the
#: layers above this one from the package's base, docs/reference/architecture.md). A name that differs
#: from the function's own is given as ``module:function``: ``mapless.train`` and ``mapless.evaluate``
#: are subpackages, which importing their modules binds to those names.
_EXPORTS = {
    "make_env": "mapless.episodes.objectnav",
    "make_vec_env": "mapless.episodes.objectnav",
    "ObjectNavEnv": "mapless.episodes.objectnav",
    "scene_library": "mapless.episodes.objectnav",
    "fixed_episodes": "mapless.episodes.objectnav",
    "Episode": "mapless.sim.episode",
    "build_model": "mapless.models.registry",
    "model_names": "mapless.models.registry",
    "load_model": "mapless.checkpoint",
    "TrainConfig": "mapless.train.config",
    "load_train_config": "mapless.train.recipes",
    "train_model": "mapless.train.run:train",
    "AgentSpec": "mapless.evaluate.runner",
    "EvalSettings": "mapless.evaluate.runner",
    "evaluate_agent": "mapless.evaluate.runner:evaluate",
    "summarize": "mapless.evaluate.metrics",
    "comparison_table": "mapless.evaluate.report",
    "read_results": "mapless.evaluate.report",
    "trajectory_figure": "mapless.evaluate.figures",
    "trajectory_gif": "mapless.evaluate.figures",
}
__all__ = ["ENV_ID", "__version__", *_EXPORTS]


def __getattr__(name: str) -> object:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'mapless' has no attribute {name!r}")
    module, _, attribute = _EXPORTS[name].partition(":")
    value = getattr(importlib.import_module(module), attribute or name)
    globals()[name] = value  # later reads skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


gymnasium.register(id=ENV_ID, entry_point="mapless.episodes.objectnav:ObjectNavEnv")
