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

Configurations live in ``experiments/<experiment>_<budget>.yaml``, each read over its budget's
``experiments/budgets/<budget>.yaml`` (:class:`ExperimentConfig`).
Runs are stored under ``<runs_dir>/<model>__<variant>__s<seed>__<hash>`` where the hash covers the
whole training configuration, so experiments share identical runs (figure3 reuses table1's).
"""

from mapless.experiments.config import (
    BUDGETS,
    EXPERIMENTS,
    ExperimentConfig,
    ExperimentEval,
    budget_path,
    config_path,
    load_experiment,
    read_experiment,
    train_config,
)
from mapless.experiments.evaluator import Evaluator, experiment_scenes
from mapless.experiments.launch import LocalLauncher, PlannedRun, SlurmLauncher
from mapless.experiments.pipelines import PIPELINES, experiment_runs, planned_runs, reproduce
from mapless.experiments.runs import RunTally, run_dir_for, train_run

__all__ = [
    "BUDGETS",
    "EXPERIMENTS",
    "PIPELINES",
    "Evaluator",
    "ExperimentConfig",
    "ExperimentEval",
    "LocalLauncher",
    "PlannedRun",
    "RunTally",
    "SlurmLauncher",
    "budget_path",
    "config_path",
    "experiment_runs",
    "experiment_scenes",
    "load_experiment",
    "planned_runs",
    "read_experiment",
    "reproduce",
    "run_dir_for",
    "train_config",
    "train_run",
]
