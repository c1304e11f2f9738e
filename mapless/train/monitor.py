"""Training metrics: TensorBoard scalars (and Weights & Biases ones, ``logger: [tensorboard, wandb]``),
``metrics.jsonl``, the tqdm progress bar and the summary a trainer's run returns (:func:`run_summary`).

Logged every ``log_every`` episodes, as means over the episodes finished since the last record
(x axis: training episodes). Keys:

* ``charts/reward``: return of an episode (sum of rewards);
* ``charts/success``: share of episodes ended by a successful ``Done``;
* ``charts/spl``: success weighted by shortest path length / max(path length, shortest), lengths in
  actions with the ``Done`` counted (SAVN's convention);
* ``charts/episode_length``: actions per episode, ``Done`` included;
* ``losses/total``, ``losses/policy``, ``losses/value``: per-episode A3C terms (sums over steps, as the
  reference), averaged over episodes; ``losses/entropy``: mean policy entropy per step (batched mode:
  over the interval's steps; async mode: the mean of its episodes' per-step means);
* ``losses/grad_norm``: L2 norm of the update's gradient before clipping (batched mode: of the mean
  over episodes and ranks; async mode: of one episode's), averaged over updates weighted by episodes;
* ``perf/frames_per_s``, ``perf/episodes_per_s``: throughput since the previous record (a frame is one
  environment step of one episode);
* ``perf/frames``: frames so far.

The progress bar shows episodes (or frames, when that is the budget), frames/s, the running success
rate of the last 1000 episodes and tqdm's ETA.

An interrupted run logs the curves of an uninterrupted one: a graceful stop (Ctrl-C, SIGTERM) writes
no record for the unfinished interval; the interval's values so far go into the checkpoint
(:meth:`RunMonitor.state`), and the resumed run completes that interval with them. Only the wall-clock
values (``perf/*_per_s``, ``time``) differ. Weights & Biases keeps a resumed run's records under the
same run id (the run folder's name); it cannot drop the records written after the checkpoint, which
the resumed run writes again (it keeps the first of each step).
"""

from __future__ import annotations

import json
import os
import re
import time
from collections import deque
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapless.checkpoint import METRICS_FILE, PROGRESS_FILE
from mapless.config import ConfigError, to_dict
from mapless.files import write_text

RUNNING_WINDOW = 1000
#: Seconds between two writes of the run folder's progress file.
PROGRESS_EVERY = 2.0


class RunMonitor:
    @classmethod
    def for_run(
        cls, run_dir: Path | None, config, counters: dict[str, int], mode: str, resume: dict | None = None
    ) -> RunMonitor:
        """The monitor of a trainer with ``config`` (a TrainConfig), resuming at ``counters`` with the
        :meth:`state` stored in the checkpoint ``resume`` (when it has one)."""
        monitor = cls(
            run_dir,
            config.log_every,
            config.episodes,
            config.frames,
            counters["episodes"],
            counters["frames"],
            progress=config.progress,
            description=f"{config.model.name} {mode}",
            loggers=tuple(config.logger),
            config=config,
        )
        saved = (resume or {}).get("monitor")
        if isinstance(saved, dict):  # checkpoints written before this field have none
            monitor._window = {str(k): [float(v) for v in values] for k, values in saved["window"].items()}
            monitor._running.extend(bool(v) for v in saved["running"])
        return monitor

    def state(self) -> dict:
        """What a resumed run needs to log as this one would have: the values of the interval in
        progress and the window of the running success rate (plain lists, for the checkpoint)."""
        return {
            "window": {key: list(values) for key, values in self._window.items()},
            "running": list(self._running),
        }

    def __init__(
        self,
        run_dir: Path | None,
        log_every: int,
        budget_episodes: int,
        budget_frames: int,
        episodes: int = 0,
        frames: int = 0,
        progress: bool = True,
        description: str = "train",
        loggers: tuple[str, ...] = ("tensorboard",),
        config=None,
    ):
        """``run_dir`` None disables every output (the non-zero ranks of a distributed run).
        ``loggers``: where the records go beside metrics.jsonl (``tensorboard``, ``wandb``); ``config``
        (the TrainConfig) is stored with a wandb run."""
        self.run_dir = run_dir
        self.log_every = log_every
        self.episodes, self.frames = episodes, frames
        self._next_log = (episodes // log_every + 1) * log_every
        self._window: dict[str, list[float]] = {}
        self._running = deque(maxlen=RUNNING_WINDOW)
        self._mark = (time.perf_counter(), episodes, frames)
        self._start = self._mark
        self._progress_written = -PROGRESS_EVERY
        self.writers: list = []
        self.bar = None
        if run_dir is None:
            return
        # Before any file is written: a missing package is an error at the start, not a late surprise.
        self.writers = [_WRITERS[name](Path(run_dir), episodes, config) for name in loggers]
        metrics = Path(run_dir) / METRICS_FILE
        if metrics.is_file():
            write_text(metrics, "".join(_records_up_to(metrics, episodes)))
        self._jsonl = open(metrics, "a")  # noqa: SIM115 - kept open for the run
        self._by_frames = budget_episodes == 0
        total = budget_frames if self._by_frames else budget_episodes
        self.bar = tqdm(
            total=total,
            initial=frames if self._by_frames else episodes,
            unit="frame" if self._by_frames else "ep",
            desc=description,
            disable=not progress,
            dynamic_ncols=True,
            smoothing=0.05,
        )

    def add_episodes(
        self, success: np.ndarray, spl: np.ndarray, length: np.ndarray, reward: np.ndarray
    ) -> None:
        for key, values in (
            ("charts/success", success),
            ("charts/spl", spl),
            ("charts/episode_length", length),
            ("charts/reward", reward),
        ):
            self._window.setdefault(key, []).extend(np.asarray(values, dtype=np.float64).tolist())
        self._running.extend(np.asarray(success, dtype=bool).tolist())

    def add_losses(
        self,
        total: float,
        policy: float,
        value: float,
        entropy: float,
        grad_norm: float,
        count: int = 1,
    ) -> None:
        """One update's loss terms and gradient norm, the losses already averaged over its ``count``
        episodes (weighted accordingly in the record)."""
        for key, value_ in (
            ("losses/total", total),
            ("losses/policy", policy),
            ("losses/value", value),
            ("losses/entropy", entropy),
            ("losses/grad_norm", grad_norm),
        ):
            self._window.setdefault(key, []).extend([float(value_)] * count)

    def add_scalars(self, values: dict[str, float], count: int = 1) -> None:
        """Further per-update scalars (PPO's approximate KL, clip fraction, ...), weighted by ``count``."""
        for key, value in values.items():
            self._window.setdefault(key, []).extend([float(value)] * count)

    @property
    def running_success(self) -> float:
        return float(np.mean(self._running)) if self._running else 0.0

    def advance(self, episodes: int, frames: int) -> dict[str, float] | None:
        """Move the counters to these totals; write a record when a log boundary was crossed."""
        delta = (
            (frames - self.frames) if self.bar is not None and self._by_frames else episodes - self.episodes
        )
        self.episodes, self.frames = episodes, frames
        if self.bar is not None:
            self.bar.update(delta)
            now, _ep0, fr0 = self._start
            fps = (frames - fr0) / max(time.perf_counter() - now, 1e-9)
            self.bar.set_postfix(
                ep=episodes, fps=f"{fps:.0f}", success=f"{self.running_success:.3f}", refresh=False
            )
        if self.run_dir is not None and time.perf_counter() - self._progress_written >= PROGRESS_EVERY:
            self._write_progress()
        if episodes < self._next_log:
            return None
        self._next_log = (episodes // self.log_every + 1) * self.log_every
        return self._write()

    def _write_progress(self) -> None:
        """The counters so far, for a process that watches this run from outside (a grid of runs
        trained side by side, or Slurm jobs): its progress line, however often the logs write."""
        self._progress_written = time.perf_counter()
        state = {"episodes": self.episodes, "frames": self.frames, "success": self.running_success}
        write_text(Path(self.run_dir) / PROGRESS_FILE, json.dumps({**state, "time": time.time()}))

    def _write(self) -> dict[str, float]:
        now = time.perf_counter()
        then, ep0, fr0 = self._mark
        elapsed = max(now - then, 1e-9)
        record = {key: float(np.mean(values)) for key, values in self._window.items() if values}
        record["perf/frames_per_s"] = (self.frames - fr0) / elapsed
        record["perf/episodes_per_s"] = (self.episodes - ep0) / elapsed
        record["perf/frames"] = float(self.frames)
        self._mark = (now, self.episodes, self.frames)
        self._window = {}
        if self.run_dir is not None:
            for writer in self.writers:
                writer.add_scalars(record, self.episodes)
            self._jsonl.write(
                json.dumps({"episodes": self.episodes, "frames": self.frames, "time": time.time(), **record})
                + "\n"
            )
            self._jsonl.flush()
        return record

    def close(self, partial_record: bool = True) -> None:
        """Write the episodes since the last record (a run stopped on time or by an error, or a budget
        that is not a multiple of ``log_every``), then close the logs. ``partial_record`` False (a
        graceful stop, to be resumed) leaves that interval to the resumed run, which completes it from
        the checkpoint's :meth:`state`: an extra record here would make its next one a short one."""
        if partial_record and any(self._window.values()):
            self._write()
        if self.run_dir is not None:
            for writer in self.writers:
                writer.close()
            self._jsonl.close()
        if self.bar is not None:
            self.bar.close()


class TensorBoardWriter:
    """The records as TensorBoard scalars in the run folder."""

    def __init__(self, run_dir: Path, episodes: int, config=None):
        from torch.utils.tensorboard import SummaryWriter

        # A resumed run continues from a checkpoint at ``episodes``, which was written after that
        # count's record: records beyond it (written before the run was killed) are dropped from
        # both logs, and the resumed run writes them again. A new run (at 0 episodes) in the folder
        # of one that wrote no checkpoint, which starts over there, drops all of that run's records.
        self.writer = SummaryWriter(log_dir=str(run_dir), purge_step=episodes + 1)

    def add_scalars(self, record: dict[str, float], episodes: int) -> None:
        for key, value in record.items():
            self.writer.add_scalar(key, value, episodes)

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()


class WandbWriter:
    """The records as a Weights & Biases run (step: training episodes), its files under the run
    folder's ``wandb/``; the project is $WANDB_PROJECT, else ``mapless``. Offline or online as wandb's
    own settings say ($WANDB_MODE=offline: no account, ``wandb sync`` uploads later)."""

    def __init__(self, run_dir: Path, episodes: int, config=None):
        try:
            import wandb
        except ImportError:
            raise ConfigError(
                "config key 'logger': wandb is not installed; pip install -c constraints.txt "
                "-e '.[wandb]' (or pip install wandb), or log to tensorboard only"
            ) from None

        self.run = wandb.init(
            dir=str(run_dir),
            project=os.environ.get("WANDB_PROJECT", "mapless"),
            name=run_dir.name,
            id=_wandb_id(run_dir),
            resume="allow",  # the same id again: a resumed run continues its wandb run
            config=to_dict(config) if config is not None else None,
            reinit="create_new",
        )

    def add_scalars(self, record: dict[str, float], episodes: int) -> None:
        self.run.log(record, step=episodes)

    def close(self) -> None:
        self.run.finish()


def _wandb_id(run_dir: Path) -> str:
    """A run folder's wandb id: its name with the characters wandb refuses replaced (it must be the
    same when the run resumes, and tell runs apart)."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", Path(run_dir).resolve().name)[:128]


#: The writer of each name a config's ``logger`` may list (mapless.train.config.LOGGERS).
_WRITERS = {"tensorboard": TensorBoardWriter, "wandb": WandbWriter}


def _records_up_to(path: Path, episodes: int) -> list[str]:
    """The lines of a metrics file whose record is at or before ``episodes`` (a line torn by a kill
    mid-write is dropped too)."""
    kept = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if record["episodes"] <= episodes:
            kept.append(line + "\n")
    return kept


def run_summary(
    counters: dict[str, int],
    start: float,
    start_frames: int,
    first: tuple[float, int] | None,
    end: float,
    running_success: float,
    stopped: bool,
) -> dict[str, float]:
    """What a trainer's ``run`` returns: its counters, the wall time, frames/s over the whole run and
    from ``first`` (time and frames after the first update, allocation warm-up excluded) to ``end``
    (the loop's end, before the final checkpoint), the running success rate and whether Ctrl-C
    stopped it early."""
    steady = (counters["frames"] - first[1]) / max(end - first[0], 1e-9) if first else 0.0
    return {
        **{k: float(v) for k, v in counters.items()},
        "seconds": time.perf_counter() - start,
        "frames_per_s": (counters["frames"] - start_frames) / max(end - start, 1e-9),
        "steady_frames_per_s": steady,
        "running_success": running_success,
        "stopped_early": float(stopped),
    }
