"""The paper's experiments as pipelines behind ``mapless reproduce EXPERIMENT --budget B``.

Each experiment's runs are trained first (launch.py: in turn, side by side in local processes, or
as Slurm jobs; skipped when a finished run of the same configuration exists), then its pipeline
(pipelines.py) selects checkpoints (``standard`` protocol: on val, reported once on test) and
evaluates, returning records (records.py); render.py writes them as ``reports/EXPERIMENT/``
(``EXPERIMENT.md``, ``EXPERIMENT.json``, PNGs):

* ``table1``: every model on the test split, ALL and L>=5 (random needs no training).
* ``table2``: cross-room-type generalisation: one run per model and training room type
  (K-single, L-single, Be-single, Ba-single), each tested on all four room types.
* ``table3``: ablation: cvmeta without the hierarchical relationships (the target->parent graph
  edges) of one room type at a time, next to the full model.
* ``figure3``: ratio-of-exploration curves of the Table 1 models (from Table 1's records).
* ``layout_shift``: the Table 1 models trained on default arrangements and on scene variants, each
  tested on the test floor plans under default and under other arrangements.
* ``figures45``: top-down trajectories of the Table 1 models on one episode where the focus model
  succeeds (Figure 4) and a failure case of the focus model (Figure 5), plus an egocentric GIF
  (from Table 1's records).

Configurations are package data (:mod:`mapless.configs`): ``<experiment>_<budget>.yaml``, each read
over its budget's ``budgets/<budget>.yaml``, or the budget as it is where the experiment has no file
(:class:`ExperimentConfig`).
Runs are stored under ``<runs_dir>/<model>__<variant>__s<seed>__<hash>`` where the hash covers the
whole training configuration, so experiments share identical runs (figure3 reuses table1's).
"""

from __future__ import annotations

import importlib
from typing import Any

# Names resolve on first use (PEP 562): the command line reads the experiment and budget names from
# config.py to build its parser, and must not pay for the evaluator's torch import while doing so.
_EXPORTS = {
    "config": (
        "BUDGETS",
        "EXPERIMENTS",
        "ExperimentConfig",
        "ExperimentEval",
        "budget_path",
        "config_path",
        "load_experiment",
        "read_experiment",
        "train_config",
    ),
    "evaluator": ("Evaluator", "experiment_scenes"),
    "launch": ("LocalLauncher", "PlannedRun", "SlurmLauncher"),
    "pipelines": ("PIPELINES", "experiment_runs", "planned_runs", "reproduce"),
    "runs": ("RunTally", "run_dir_for", "train_run"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
