"""An experiment's training runs: their folders, training (or reusing) them, and the progress log."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mapless.config import to_dict
from mapless.experiments.config import ExperimentConfig
from mapless.models.registry import model_folder_name
from mapless.train.config import TrainConfig


def run_dir_for(config: ExperimentConfig, train_cfg: TrainConfig, variant: str) -> Path:
    """``<runs_dir>/<model>__<variant>__s<seed>__<hash>``, the hash over what the run trains with
    (:func:`run_hash`), so experiments with an identical run share it."""
    model = model_folder_name(train_cfg.model.name)
    return Path(config.runs_dir) / f"{model}__{variant}__s{train_cfg.seed}__{run_hash(train_cfg)}"


def run_hash(train_cfg: TrainConfig) -> str:
    """Eight hex digits of the SHA-256 of the training config as it is laid out, less what changes
    no run: the progress bar and where the records go (``logger``)."""
    return config_hash(hashed_config(train_cfg))


def hashed_config(train_cfg: TrainConfig) -> dict:
    """What a run hash reads of ``train_cfg``: all of it but the progress bar and the logger."""
    data = to_dict(dataclasses.replace(train_cfg, progress=False))
    del data["logger"]
    return data


def config_hash(data: dict) -> str:
    """Eight hex digits of the SHA-256 of a config mapping's JSON with sorted keys."""
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:8]


@dataclass
class RunTally:
    """Logs ``[run i of N]`` as each of an experiment's runs starts and, once one has been trained,
    the time left. Per model: the mean wall time of a run's training over the runs of that model
    this process trained, a resumed run's time scaled up by the share of its
    episodes trained here, times that model's runs left. Models differ by far (at the small budget an
    mlp run ends at its frame budget in about 4 minutes, an a3c one at its 15), so a model with runs left but none timed yet is
    named, and the estimate covers the others only. Reused runs take seconds, so while some are left
    the estimate is an upper bound."""

    planned: dict[str, int]  # model -> runs (pipelines.planned_runs)
    log: Callable[[str], None]
    finished: Counter[str] = field(default_factory=Counter)
    run_seconds: dict[str, list[float]] = field(default_factory=dict)  # per whole run, as estimated
    _model: str = ""
    _started: float = 0.0

    def start(self, model: str, what: str) -> None:
        """Log the start of a run of ``model`` (``what``: the rest of its description)."""
        done, total = sum(self.finished.values()), sum(self.planned.values())
        self.log(f"[run {done + 1} of {total}] {model} {what}{self._time_left()}")
        self._model, self._started = model, time.perf_counter()

    def finish(self, trained_share: float) -> None:
        """``trained_share``: the share of the run's episodes trained by this process (0: reused)."""
        self.finished[self._model] += 1
        if trained_share > 0:
            seconds = (time.perf_counter() - self._started) / trained_share
            self.run_seconds.setdefault(self._model, []).append(seconds)

    def _time_left(self) -> str:
        per_run = {model: sum(s) / len(s) for model, s in self.run_seconds.items()}
        if not per_run:
            return ""
        left = Counter(self.planned) - self.finished  # runs not finished, per model (none: absent)
        seconds = sum(per_run[model] * n for model, n in left.items() if model in per_run)
        each = ", ".join(f"{_duration(s)} per {model} run" for model, s in per_run.items())
        untimed = [model for model in left if model not in per_run]
        if not untimed:
            return f"; about {_duration(seconds)} left ({each})"
        timed = [model for model in left if model in per_run]
        known = f"about {_duration(seconds)} left for {', '.join(timed)}; " if timed else ""
        return f"; {known}no {', '.join(untimed)} run timed yet ({each})"


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"


def train_run(train_cfg: TrainConfig, run_dir: Path, log: Callable[[str], None]) -> float:
    """Train unless ``run_dir`` already holds a finished run (its final model); an interrupted run
    (a resumable checkpoint but no final model) is resumed. Returns the share of the run's episodes
    trained here: 0 for a reused run, 1 for one trained from the start."""
    from mapless import checkpoint as ckpt
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
