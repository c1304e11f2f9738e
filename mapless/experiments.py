"""The paper's experiments as pipelines behind ``mapless reproduce EXPERIMENT --budget B``.

Each experiment trains its runs (skipped when a finished run of the same configuration exists),
selects checkpoints (``standard`` protocol: on val, reported once on test), evaluates, and writes
``reports/EXPERIMENT/`` (``EXPERIMENT.md``, ``EXPERIMENT.json``, PNGs):

* ``table1``: every model on the test split, ALL and L>=5 (random needs no training).
* ``table2``: cross-room-type generalisation: one run per model and training room type
  (K-single, L-single, Be-single, Ba-single), each tested on all four room types.
* ``table3``: ablation: cvmeta without the hierarchical relationships (the target->parent graph
  edges) of one room type at a time, next to the full model.
* ``figure3``: ratio-of-exploration curves of the Table 1 models.
* ``figures45``: top-down trajectories of the Table 1 models on one episode where the focus model
  succeeds (Figure 4) and a failure case of the focus model (Figure 5), plus an egocentric GIF.

Configurations live in ``experiments/<experiment>_<budget>.yaml`` (:class:`ExperimentConfig`).
Runs are stored under ``<runs_dir>/<model>__<variant>__s<seed>__<hash>`` where the hash covers the
whole training configuration, so experiments share identical runs (figure3 reuses table1's).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Literal

from mapless.config import ConfigError, apply_overrides, from_dict, load_config, to_dict
from mapless.errors import MaplessError, UnknownNameError
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.report import (
    COLUMNS,
    MAIN_COLUMNS,
    ROOM_NAMES,
    details_table,
    difference_record,
    format_difference,
    format_estimate,
    markdown,
    model_record,
    model_table,
    room_table,
    write_json,
)
from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate
from mapless.evaluate.selection import PROTOCOLS, load_episodes, select_and_report
from mapless.evaluate.stats import seed_estimates
from mapless.files import write_text
from mapless.scenes.catalogue import ROOM_TYPES

EXPERIMENTS = ("table1", "table2", "table3", "figure3", "figures45")
BUDGETS = ("smoke", "small", "full")
ROOM_ABBREV = {"kitchen": "K", "living_room": "L", "bedroom": "Be", "bathroom": "Ba"}


@dataclass(frozen=True)
class ExperimentEval:
    """How runs are evaluated.

    protocol: ``standard`` (select on val, report on test) or ``paper`` (select and report on x21-x30).
    per_room: the first N episodes per room type of the fixed sets (250 = all).
    select: evaluate every checkpoint and select (False: the final model only).
    select_file / report_file: episode files replacing the built-in val / test sets (tests).
    """

    protocol: Literal["standard", "paper"] = "standard"
    per_room: int = 250
    rooms: tuple[str, ...] = ROOM_TYPES
    select: bool = True
    select_file: str | None = None
    report_file: str | None = None
    batch_size: int = 32
    workers: int = 2
    seed: int = 0
    greedy: bool = False


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment at one budget.

    models: the compared models (Table 1/2, figures); Table 3 always ablates ``focus``.
    seeds: training seeds per run (mean ± std over them).
    train: TrainConfig fields shared by every run (nested mapping, validated by TrainConfig).
    per_model: TrainConfig overrides per model name (e.g. a smaller batch for the meta models).
    rooms: room types of Table 2 (training rooms) and Table 3 (ablated rooms).
    focus: the paper's model (cvmeta), for Table 3 and the showcase figures.
    runs_dir: where training runs go (shared between experiments).
    single_room_scenes: Table 2's training scenes per room type (default ``train:<room>``, the 20
        training floor plans of the room).
    """

    experiment: str = "table1"
    budget: str = "smoke"
    models: tuple[str, ...] = ("random", "a3c", "cvmeta")
    seeds: int = 1
    train: dict = field(default_factory=dict)
    per_model: dict = field(default_factory=dict)
    eval: ExperimentEval = field(default_factory=ExperimentEval)
    rooms: tuple[str, ...] = ROOM_TYPES
    focus: str = "cvmeta"
    runs_dir: str = "runs/experiments"
    gif: bool = True
    single_room_scenes: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.experiment not in EXPERIMENTS:
            raise UnknownNameError("experiment", self.experiment, EXPERIMENTS)
        if self.seeds < 1:
            raise ConfigError(f"config key 'seeds': must be >= 1, got {self.seeds}")
        from mapless.models import MODELS

        for name in (*self.models, self.focus):
            if name not in MODELS:
                raise UnknownNameError("model", name, MODELS)
        for room in (*self.rooms, *self.eval.rooms):
            if room not in ROOM_TYPES:
                raise UnknownNameError("room type", room, ROOM_TYPES)


def config_path(experiment: str, budget: str, root: Path | None = None) -> Path:
    """``experiments/<experiment>_<budget>.yaml`` of the repository (or of ``root``)."""
    base = root or Path(str(resources.files("mapless"))).parent / "experiments"
    return base / f"{experiment}_{budget}.yaml"


def load_experiment(
    experiment: str,
    budget: str,
    path: Path | None = None,
    overrides: list[str] | None = None,
    seeds: int | None = None,
) -> ExperimentConfig:
    path = path or config_path(experiment, budget)
    if not path.is_file():
        raise MaplessError(
            f"no experiment config {path} (experiments: {', '.join(EXPERIMENTS)}; budgets: {', '.join(BUDGETS)})"
        )
    extra = [*(overrides or []), *([f"seeds={seeds}"] if seeds else [])]
    config = load_config(ExperimentConfig, path, extra)
    if config.experiment != experiment:
        raise ConfigError(f"{path} configures {config.experiment!r}, not {experiment!r}")
    return config


# -- training ----------------------------------------------------------------------------------------
def train_config(config: ExperimentConfig, model: str, seed: int, extra: dict | None = None):
    """The TrainConfig of one run: shared ``train`` <- ``per_model[model]`` <- ``extra``, model and seed."""
    from mapless.train.config import TrainConfig

    data = json.loads(json.dumps(config.train))
    for layer in (config.per_model.get(model, {}), extra or {}):
        data = _merge(data, layer)
    data = apply_overrides(data, [f"model.name={model}", f"seed={seed}"])
    return from_dict(TrainConfig, data)


def _merge(base: dict, top: dict) -> dict:
    out = dict(base)
    for key, value in top.items():
        out[key] = (
            _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
        )
    return out


def run_dir_for(config: ExperimentConfig, train_cfg, variant: str) -> Path:
    blob = json.dumps(to_dict(dataclasses.replace(train_cfg, progress=False)), sort_keys=True)
    digest = hashlib.sha256(blob.encode()).hexdigest()[:8]
    return Path(config.runs_dir) / f"{train_cfg.model.name}__{variant}__s{train_cfg.seed}__{digest}"


def planned_runs(config: ExperimentConfig) -> int:
    """How many training runs an experiment goes through (finished ones are reused, not retrained)."""
    if config.experiment == "table3":  # the focus model, then without one room type at a time
        return (1 + len(config.rooms)) * config.seeds
    trained = sum(model != "random" for model in config.models)
    per_model = len(config.rooms) if config.experiment == "table2" else 1
    return trained * per_model * config.seeds


@dataclass
class RunTally:
    """Logs ``[run i of N]`` as each of an experiment's runs starts and, once one has been trained,
    the time left: the mean wall time of a whole run (training and evaluation) over the runs this
    process trained, a resumed run's time scaled up by the share of its episodes trained here, times
    the runs left. Reused runs take seconds, so while some are left it is an upper bound."""

    total: int
    log: Callable[[str], None]
    done: int = 0
    run_seconds: list[float] = field(default_factory=list)  # per whole run, as estimated
    _started: float = 0.0

    def start(self, what: str) -> None:
        left = ""
        if self.run_seconds:
            each = sum(self.run_seconds) / len(self.run_seconds)
            left = f"; about {_duration(each * (self.total - self.done))} left ({_duration(each)} per trained run)"
        self.log(f"[run {self.done + 1} of {self.total}] {what}{left}")
        self._started = time.perf_counter()

    def finish(self, trained_share: float) -> None:
        """``trained_share``: the share of the run's episodes trained by this process (0: reused)."""
        self.done += 1
        if trained_share > 0:
            self.run_seconds.append((time.perf_counter() - self._started) / trained_share)


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def train_run(train_cfg, run_dir: Path, log: Callable[[str], None]) -> float:
    """Train unless ``run_dir`` already holds a finished run (its final model); an interrupted run
    (a resumable checkpoint but no final model) is resumed. Returns the share of the run's episodes
    trained here: 0 for a reused run, 1 for one trained from the start."""
    from mapless.train import checkpoint as ckpt
    from mapless.train.run import train

    if (run_dir / ckpt.FINAL_MODEL_FILE).is_file():
        log(f"  reusing finished run {run_dir}")
        return 0.0
    resume, start = None, 0
    if (run_dir / ckpt.CHECKPOINT_FILE).is_file():
        resume = ckpt.load_file(run_dir / ckpt.CHECKPOINT_FILE)
        start = int(resume.get("counters", {}).get("episodes", 0))
        log(f"  resuming {run_dir} at {start} episodes")
    else:
        log(f"  training {train_cfg.model.name} (seed {train_cfg.seed}) -> {run_dir}")
    stats = train(train_cfg, run_dir, resume=resume)
    log(
        f"    {stats.get('episodes', 0):.0f} episodes, {stats.get('frames', 0):.0f} frames in {stats.get('seconds', 0):.0f} s"
    )
    if stats.get("stopped_early"):
        # Ctrl-C stopped the run at a checkpoint: the experiment stops too, rather than evaluate and
        # report a half-trained model as if it were the finished run.
        log(f"  stopped early; {run_dir} is kept and the same command resumes it")
        raise KeyboardInterrupt
    return 1.0 - start / max(stats.get("episodes", 0), 1)


# -- evaluation --------------------------------------------------------------------------------------
def experiment_scenes(config: ExperimentConfig) -> tuple[LibrarySpec, str]:
    """The scenes (simulator settings) and target set of an experiment: those of its focus model's
    training config. The untrained baselines and the figures use them too."""
    env = train_config(config, config.focus, seed=1).env
    return LibrarySpec.for_env(env), env.target_set


@dataclass
class Evaluator:
    """Evaluation settings and episode sets of one experiment."""

    config: ExperimentConfig
    log: Callable[[str], None]

    def __post_init__(self) -> None:
        e = self.config.eval
        select_split, report_split, self.protocol_label = PROTOCOLS[e.protocol]
        self.settings = EvalSettings(batch_size=e.batch_size, workers=e.workers, seed=e.seed, greedy=e.greedy)
        self.scenes, target_set = experiment_scenes(self.config)
        self._untrained: dict[str, tuple[list[EpisodeResult], dict]] = {}
        sets = {"per_room": e.per_room, "rooms": e.rooms, "library": self.scenes, "target_set": target_set}
        self.select_episodes = load_episodes(select_split, e.select_file, **sets)
        self.report_episodes = (
            self.select_episodes
            if e.protocol == "paper"
            else load_episodes(report_split, e.report_file, **sets)
        )

    def library(self, train_cfg) -> LibrarySpec:
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

    def trained(self, run_dir: Path, train_cfg) -> tuple[list[EpisodeResult], dict]:
        settings = dataclasses.replace(self.settings, category_set=train_cfg.model.category_set)
        if self.config.eval.select:
            sel = select_and_report(
                run_dir, self.select_episodes, self.report_episodes, settings, self.library(train_cfg),
                self.config.eval.protocol, progress=self.log,
            )  # fmt: skip
            self.log(f"  chose {Path(sel.chosen).name} ({sel.chosen_episodes} training episodes)")
            return sel.report.results, {
                "selection": sel.summary(),
                "steps_per_second": sel.report.steps_per_second,
            }
        from mapless.train.checkpoint import resolve_model_file

        spec = AgentSpec(checkpoint=str(resolve_model_file(run_dir)))
        run = evaluate(spec, self.report_episodes, settings, self.library(train_cfg))
        return run.results, {"steps_per_second": run.steps_per_second}


def _model_results(config: ExperimentConfig, ev: Evaluator, tally: RunTally, model: str, variant: str = "all",
                   extra: dict | None = None, log: Callable[[str], None] = print) -> tuple[list[list[EpisodeResult]], list[dict]]:  # fmt: skip
    """Per-seed report results of one model (trained per seed, or untrained for ``random``)."""
    per_seed, meta = [], []
    if model == "random":
        results, info = ev.untrained(model)
        return [results], [info]
    for s in range(config.seeds):
        cfg = train_config(config, model, seed=1 + s, extra=extra)
        run_dir = run_dir_for(config, cfg, variant)
        tally.start(f"{model} {variant}, seed {1 + s}")
        trained_share = train_run(cfg, run_dir, log)
        results, info = ev.trained(run_dir, cfg)
        tally.finish(trained_share)
        per_seed.append(results)
        meta.append({"run_dir": str(run_dir), **info})
    return per_seed, meta


def _header(config: ExperimentConfig, title: str, ev: Evaluator, command: str) -> list[str]:
    return [
        f"# {title}",
        "",
        f"Budget `{config.budget}`, {config.seeds} training seed(s); {len(ev.report_episodes)} report episodes "
        f"({config.eval.per_room} per room type); protocol: {ev.protocol_label}.",
        f"Command: `{command}`; finished {time.strftime('%Y-%m-%d %H:%M')}.",
        "Cells: mean (± std over seeds) [95 % bootstrap interval over episodes], in %.",
        "",
    ]


def run_table1(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    records, results = [], {}
    for model in config.models:
        log(f"{model}:")
        per_seed, meta = _model_results(config, ev, tally, model, log=log)
        records.append(model_record(model, per_seed, {"runs": meta, "protocol": config.eval.protocol}))
        results[model] = per_seed
    if config.focus in results:
        for rec in records:
            if rec["model"] != config.focus:
                rec["focus_minus_model"] = difference_record(results[rec["model"]], results[config.focus])
    lines = _header(config, "Table 1: navigation results on unseen scenes", ev, command)
    lines += [model_table(records), "", *_focus_differences(config.focus, records)]
    lines += ["Secondary metrics (mean over seeds):", "", details_table(records), ""]
    for rec in records:
        lines += [f"Per room type, {rec['model']}:", "", room_table(rec), ""]
    return {**_finish(config, ev, out, lines, models=records), "results": results}


def _focus_differences(focus: str, records: list[dict]) -> list[str]:
    """Table 1's comparison of the focus model with each other model, if it has one."""
    key = "focus_minus_model"
    rows = [
        [rec["model"], *(format_difference(c, rec[key][c]) for c in MAIN_COLUMNS)]
        for rec in records
        if key in rec
    ]
    if not rows:
        return []
    header = ["model", *(f"Δ {COLUMNS[c][0]}" for c in MAIN_COLUMNS)]
    return [
        f"{focus} minus each model, in points, with the 95 % interval of the difference over episodes "
        "(paired: the same episodes) and each model's training seeds:",
        "",
        markdown(header, rows),
        "",
    ]


def run_table2(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    """Rows: model x training room type; columns: SR / SPL on each test room type and overall."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    rows, records = [], []
    header = [
        "model",
        "trained on",
        *(f"{ROOM_NAMES[r]} SR / SPL" for r in config.eval.rooms),
        "All SR / SPL",
    ]
    for model in config.models:
        for room in config.rooms:
            log(f"{model}, {ROOM_ABBREV[room]}-single:")
            extra = {"env": {"scenes": config.single_room_scenes.get(room, f"train:{room}")}}
            per_seed, meta = _model_results(
                config, ev, tally, model, f"{ROOM_ABBREV[room]}-single", extra, log
            )
            rec = model_record(
                f"{model} {ROOM_ABBREV[room]}-single",
                per_seed,
                {"runs": meta, "train_room": room},
                keep_episodes=False,
            )
            records.append(rec)
            cells = []
            for test_room in config.eval.rooms:
                est = rec["rooms"].get(test_room)
                cells.append(_pair(est))
            rows.append([model, f"{ROOM_ABBREV[room]}-single", *cells, _pair(rec["estimates"])])
    lines = _header(
        config, "Table 2: generalisation across room types (train on one, test on all)", ev, command
    )
    lines += [markdown(header, rows), ""]
    return _finish(config, ev, out, lines, runs=records)


def _finish(config: ExperimentConfig, ev: Evaluator, out: Path, lines: list[str], **results) -> dict:
    """Write the experiment's JSON and markdown report; return both."""
    payload = {
        "experiment": config.experiment,
        "config": to_dict(config),
        "protocol": ev.protocol_label,
        **results,
    }
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


def _pair(estimates: dict | None) -> str:
    """``SR [95 % interval] / SPL`` of one cell (the SPL interval is left to the JSON, for width)."""
    if not estimates:
        return "–"
    return f"{format_estimate('success', estimates['success'])} / {format_estimate('spl', estimates['spl'], False)}"


def run_table3(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    """The focus model with every room's relationships, then without those of one room type."""
    ev, tally = Evaluator(config, log), RunTally(planned_runs(config), log)
    variants = [("full", None)] + [(room, tuple(r for r in ROOM_TYPES if r != room)) for room in config.rooms]
    records, full = [], None
    for name, rooms in variants:
        label = config.focus if rooms is None else f"{ROOM_NAMES[name].replace(' ', '_')}_no_relationships"
        log(f"{label}:")
        extra = (
            None
            if rooms is None
            else {"model": {"hierarchy_rooms": list(rooms)}, "env": {"parent_reward_rooms": list(rooms)}}
        )
        # The unablated model is Table 1's run (variant "all", same configuration): trained once.
        per_seed, meta = _model_results(
            config, ev, tally, config.focus, "all" if rooms is None else f"no-{name}", extra, log
        )
        rec = model_record(
            label,
            per_seed,
            {"runs": meta, "removed_room": None if rooms is None else name},
            keep_episodes=False,
        )
        if rooms is None:
            full = per_seed
        else:
            rec["minus_full"] = {
                "all": difference_record(full, per_seed),
                name: difference_record(full, per_seed, name),
            }
        records.append(rec)
    header = ["model", *(f"{ROOM_NAMES[r]} SR / SPL" for r in config.eval.rooms), "All SR / SPL"]
    rows = [
        [rec["model"], *(_pair(rec["rooms"].get(r)) for r in config.eval.rooms), _pair(rec["estimates"])]
        for rec in records
    ]
    lines = _header(config, "Table 3: ablation of the hierarchical relationships", ev, command)
    lines += [
        "Each `<Room>_no_relationships` run drops the target->parent edges that only that room type's hierarchy adds to the graph (pairs the VG graph or another room type also links stay) and its parent-object reward.",
        "",
        markdown(header, rows),
        "",
        model_table(records),
        "",
        "Each ablation minus the full model, in points, with the 95 % interval of the difference over "
        "episodes (paired: the same episodes) and both runs' training seeds; the paper's claim is a "
        "drop, largest on the room type whose relationships were removed:",
        "",
        markdown(
            ["model", "Δ SR", "Δ SPL", "Δ SR, its room type", "Δ SPL, its room type"],
            [
                [rec["model"], *_ablation_cells(rec["minus_full"], rec["removed_room"])]
                for rec in records
                if "minus_full" in rec
            ],
        ),
        "",
    ]
    return _finish(config, ev, out, lines, models=records)


def _ablation_cells(minus_full: dict, room: str) -> list[str]:
    return [format_difference(c, minus_full[part][c]) for part in ("all", room) for c in ("success", "spl")]


def run_figure3(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    from mapless.evaluate.figures import exploration_figure

    table = run_table1(dataclasses.replace(config, experiment="table1"), out / "table1", log, command)
    pooled = {m: [r for seed in per_seed for r in seed] for m, per_seed in table["results"].items()}
    curves = exploration_figure(pooled, out / "figure3_exploration.png")
    ratios = {m: seed_estimates(per_seed)["exploration_ratio"] for m, per_seed in table["results"].items()}
    lines = [
        "# Figure 3: ratio of exploration",
        "",
        "Distinct states explored / steps taken, per step index, averaged over the episodes still running.",
        f"Command: `{command}`.",
        "",
        "![ratio of exploration](figure3_exploration.png)",
        "",
        markdown(
            ["model", "final ratio (episode mean)"],
            [[m, format_estimate("exploration_ratio", e)] for m, e in ratios.items()],
        ),
        "",
    ]
    payload = {
        "experiment": config.experiment,
        "curves": curves,
        "final_ratio": {m: e.to_dict() for m, e in ratios.items()},
    }
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


def run_figures45(config: ExperimentConfig, out: Path, log: Callable[[str], None], command: str) -> dict:
    from mapless.evaluate.figures import pick_showcase, trajectory_figure, trajectory_gif
    from mapless.knowledge import parents_of

    table = run_table1(dataclasses.replace(config, experiment="table1"), out / "table1", log, command)
    first_seed = {m: per_seed[0] for m, per_seed in table["results"].items()}
    focus = config.focus if config.focus in first_seed else next(iter(first_seed))
    showcase, failure = pick_showcase(first_seed, focus)
    library = experiment_scenes(config)[0].build()
    lines = ["# Figures 4 and 5: trajectories", "", f"Command: `{command}`.", ""]
    figures = {}
    for name, index, caption in (
        ("figure4_trajectories", showcase, f"{focus} succeeds; the other models on the same episode"),
        ("figure5_failure", failure, f"a failure case of {focus}"),
    ):
        if index is None:
            lines += [f"No episode for {name} ({caption}) in this run.", ""]
            continue
        chosen = {m: next(r for r in res if r.index == index) for m, res in first_seed.items()}
        episode = chosen[focus]
        parents = tuple(parents_of(episode.room_type, episode.target))
        trajectory_figure(chosen, library, out / f"{name}.png", parents=parents)
        figures[name] = {"index": index, "episode_id": episode.episode_id, "scene": episode.scene, "target": episode.target,
                         "parents": list(parents), "outcomes": {m: {"success": r.success, "length": r.length} for m, r in chosen.items()}}  # fmt: skip
        lines += [f"## {name}: {caption}", "", f"{episode.scene}, target {episode.target}, parents {', '.join(parents) or '–'}.", "",
                  f"![{name}]({name}.png)", ""]  # fmt: skip
        if config.gif and name == "figure4_trajectories":
            trajectory_gif(episode, library, out / f"{name}_{focus}.gif", every=1)
            lines += [f"Egocentric views of {focus}: `{name}_{focus}.gif`.", ""]
    payload = {"experiment": config.experiment, "figures": figures}
    _write(out, config.experiment, payload, lines)
    return {"payload": payload, "markdown": "\n".join(lines)}


PIPELINES: dict[str, Callable[..., dict]] = {
    "table1": run_table1,
    "table2": run_table2,
    "table3": run_table3,
    "figure3": run_figure3,
    "figures45": run_figures45,
}


def _write(out: Path, name: str, payload: dict, lines: list[str]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json(payload, out / f"{name}.json")
    write_text(out / f"{name}.md", "\n".join(lines))


def reproduce(config: ExperimentConfig, reports_dir: Path = Path("reports"), log: Callable[[str], None] = print,
              command: str = "") -> dict:  # fmt: skip
    """Run one experiment end to end; returns the pipeline's payload and markdown."""
    out = Path(reports_dir) / config.experiment
    start = time.perf_counter()
    result = PIPELINES[config.experiment](
        config, out, log, command or f"mapless reproduce {config.experiment} --budget {config.budget}"
    )
    log(f"{config.experiment}: done in {time.perf_counter() - start:.0f} s; report in {out}")
    return result
