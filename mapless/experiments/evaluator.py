"""How an experiment evaluates: its scenes, episode sets and settings, untrained baselines once,
trained runs with checkpoint selection."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mapless.episodes.evalsets import describe_untrained, set_path, untrained_targets
from mapless.episodes.protocols import get_protocol
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import load_episodes
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate
from mapless.evaluate.selection import cached_evaluate, evaluate_run
from mapless.experiments.config import ExperimentConfig, train_config
from mapless.scenes.categories import TARGET_SETS
from mapless.sim.episode import Episode
from mapless.train.config import TrainConfig


def experiment_scenes(config: ExperimentConfig) -> tuple[LibrarySpec, str]:
    """The scenes (simulator settings) and target set of an experiment: those of its focus model's
    training config. The untrained baselines and the figures use them too."""
    env = train_config(config, config.focus, seed=1).env
    return LibrarySpec.for_env(env), env.target_set


def trained_target_sets(config: ExperimentConfig) -> dict[str, str]:
    """The training target set of each trained model of an experiment (and of each ablation row)."""
    runs = {m: train_config(config, m, 1) for m in sorted({*config.models, config.focus} - {"random"})}
    if config.experiment == "ablation":
        for name, row in config.ablation_table().items():
            runs[f"{config.focus} ({name})"] = train_config(config, config.focus, 1, row.train)
    return {name: cfg.env.target_set for name, cfg in runs.items()}


def refuse_untrained_targets(config: ExperimentConfig, sets: dict[str, tuple[str, list[Episode]]]) -> None:
    """Refuses an experiment whose episode sets (``{role: (source, episodes)}``) hold targets that one
    of its trained runs never trains for: its table would score them on classes they never saw as
    targets. Called before any training; the error names the fix."""
    trained = trained_target_sets(config)
    for role, (source, episodes) in sets.items():
        for model, target_set in trained.items():
            found = untrained_targets(episodes, target_set)
            if not found:
                continue
            fits = [name for name in TARGET_SETS if not untrained_targets(episodes, name)]
            fix = " or ".join(f"--set train.env.target_set={name}" for name in fits)
            raise MaplessError(
                f"the {role} episodes ({source}) do not fit the {model} runs: "
                f"{describe_untrained(found, len(episodes), target_set)}. Either train on the episodes' "
                f"targets ({fix or 'no target set has them all'}), "
                f"or evaluate on episodes of target set {target_set}: leave eval.select_file and "
                "eval.report_file unset (the sets of the training target set) or give files of its targets"
            )


@dataclass
class Evaluator:
    """Evaluation settings and episode sets of one experiment."""

    config: ExperimentConfig
    log: Callable[[str], None]

    def __post_init__(self) -> None:
        e = self.config.eval
        protocol = get_protocol(e.protocol)
        self.protocol_label = protocol.label
        self.settings = EvalSettings(batch_size=e.batch_size, workers=e.workers, seed=e.seed, greedy=e.greedy)
        self.scenes, target_set = experiment_scenes(self.config)
        self._untrained: dict[str, tuple[list[EpisodeResult], dict]] = {}
        sets = {"rooms": e.rooms, "library": self.scenes, "target_set": target_set}
        # A protocol that selects and reports on the same episodes (paper) keeps them the same.
        same_episodes = protocol.select_split == protocol.report_split
        select_per_room = e.per_room if same_episodes else e.select_per_room or e.per_room
        self.select_episodes = load_episodes(
            protocol.select_split, e.select_file, per_room=select_per_room, **sets
        )
        self.report_episodes = (
            self.select_episodes
            if same_episodes
            else load_episodes(protocol.report_split, e.report_file, per_room=e.per_room, **sets)
        )
        # The sets follow the training target set; a file given in their place must fit it too.
        select_source = set_path(protocol.select_split, target_set, episodes_file=e.select_file).name
        report_source = set_path(protocol.report_split, target_set, episodes_file=e.report_file).name
        refuse_untrained_targets(
            self.config,
            {
                "selection": (select_source, self.select_episodes),
                "report": (report_source, self.report_episodes),
            },
        )
        if not (e.select_file or e.report_file):
            self.protocol_label = f"{protocol.label}; the episodes of target set {target_set}"
        if self.config.experiment == "layout_shift" and e.shift_file:
            refuse_untrained_targets(self.config, {"layout-shift": (e.shift_file, self.shift_episodes)})

    @functools.cached_property
    def shift_episodes(self) -> list[Episode]:
        """The report split under other arrangements (the layout-shift experiment): ``eval.shift_file``,
        else the ``eval.shift_layouts`` set, shipped or made on the spot."""
        e = self.config.eval
        split = get_protocol(e.protocol).report_split
        target_set = experiment_scenes(self.config)[1]
        return load_episodes(
            split, e.shift_file, e.per_room, e.rooms, self.scenes, target_set,
            layouts=None if e.shift_file else e.shift_layouts,
        )  # fmt: skip

    def chosen_model(self, run_dir: Path, info: dict) -> str:
        """The model file :meth:`trained` reported with: the selected snapshot, or the final model."""
        if "selection" in info:
            return info["selection"]["chosen"]
        from mapless.checkpoint import resolve_model_file

        return str(resolve_model_file(run_dir))

    def on(
        self,
        episodes: list[Episode],
        model: str,
        train_cfg: TrainConfig | None = None,
        checkpoint: str | None = None,
        cache: Path | None = None,
        adapt: bool = True,
    ) -> list[EpisodeResult]:
        """One agent (an untrained ``model``, or a ``checkpoint`` of a run) on other ``episodes``;
        ``cache``: a file that keeps the results for the same checkpoint, episodes and settings;
        ``adapt``: test-time adaptation of an adaptive model (False: its θ_0, never adapted)."""
        if checkpoint is None:
            return evaluate(AgentSpec(model={"name": model}), episodes, self.settings, self.scenes).results
        if train_cfg is None:
            raise ValueError("a checkpoint is evaluated with its run's training config (train_cfg)")
        settings = dataclasses.replace(self.settings, category_set=train_cfg.model.category_set)
        spec, library = AgentSpec(checkpoint=checkpoint, adapt=adapt), self.library(train_cfg)
        return cached_evaluate(spec, episodes, settings, library, cache).results

    def library(self, train_cfg: TrainConfig) -> LibrarySpec:
        """A run's scenes; they must be the experiment's, which its episode sets were checked against."""
        spec = LibrarySpec.for_env(train_cfg.env)
        if spec.sim_fingerprint != self.scenes.sim_fingerprint:
            raise MaplessError(
                f"the {train_cfg.model.name} run's simulator settings differ from the experiment's "
                f"({self.config.focus}'s), on which its episode sets were checked; give every model the same env.sim"
            )
        return spec

    def untrained(self, model: str) -> tuple[list[EpisodeResult], dict]:
        """An untrained baseline's results, evaluated once per experiment (Table 2 lists it per
        training room type, with the same episodes and seed)."""
        if model not in self._untrained:
            run = evaluate(AgentSpec(model={"name": model}), self.report_episodes, self.settings, self.scenes)
            self.log(f"  {model}: {len(run.results)} episodes, {run.steps_per_second:.0f} steps/s")
            self._untrained[model] = (run.results, {"steps_per_second": run.steps_per_second})
        return self._untrained[model]

    def trained(
        self, run_dir: Path, train_cfg: TrainConfig, within_minutes: float | None = None
    ) -> tuple[list[EpisodeResult], dict]:
        """A trained run's report results: its checkpoint chosen on the selection episodes (among
        those of its first ``within_minutes`` of training), or its final model when the experiment
        does not select."""
        settings = dataclasses.replace(self.settings, category_set=train_cfg.model.category_set)
        select = self.select_episodes if self.config.eval.select else None
        library, protocol = self.library(train_cfg), self.config.eval.protocol
        done = evaluate_run(
            run_dir, self.report_episodes, settings, library, select, protocol, self.log,
            within_minutes=within_minutes,
        )  # fmt: skip
        info: dict = {"steps_per_second": done.report.steps_per_second}
        if done.selection is not None:
            self.log(
                f"  chose {Path(done.model_file).name} ({done.selection.chosen_episodes} training episodes)"
            )
            info = {"selection": done.selection.summary(), **info}
        return done.report.results, info


@dataclass(frozen=True)
class EvaluateInLane:
    """A finished run's evaluation as the experiment will do it (selection and report), run in a
    lane of the training grid that has no run left to train
    (:attr:`~mapless.experiments.launch.LocalLauncher.evaluate_early`): one worker, the lane's
    core; the results are cached in the run's folder, where the experiment's evaluation reads
    them back (the worker count is not part of what they depend on)."""

    config: ExperimentConfig

    def __call__(self, run, log: Callable[[str], None]) -> None:
        one_worker = dataclasses.replace(self.config.eval, workers=1)
        Evaluator(dataclasses.replace(self.config, eval=one_worker), log).trained(run.run_dir, run.config)
