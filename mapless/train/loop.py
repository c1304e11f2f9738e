"""The loop every trainer runs (batched, PPO, Hogwild): counters, the budget (episodes, frames,
wall-clock), the checkpoint schedule, the run's monitor, a graceful stop on Ctrl-C or SIGTERM and
the run summary. A trainer supplies only what differs: how it sets up (``_setup``), one unit of
work counted with ``_count`` (``_train_step``), its random streams for the checkpoint
(``_rng_states``) and, if it has any, the processes it starts and stops around the loop."""

from __future__ import annotations

import abc
import time
from pathlib import Path
from typing import Any

from mapless import checkpoint as ckpt
from mapless.train.config import TrainConfig
from mapless.train.gradients import check_finite
from mapless.train.monitor import RunMonitor, run_summary
from mapless.train.runtime import GracefulStop


class TrainingLoop(abc.ABC):
    """Owns the run from setup to summary; subclasses set ``model`` and ``optimizer`` in ``_setup``."""

    label = "trainer"  # the progress bar's and the logs' name for the trainer
    model: Any
    optimizer: Any

    def __init__(self, config: TrainConfig, run_dir: Path | None):
        self.config = config
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.counters = {"episodes": 0, "frames": 0, "updates": 0}
        self._clock = time.perf_counter()
        self._snapshot_due = False  # the last update crossed a checkpoint boundary, not yet written
        # Episodes, frames and seconds at the last checkpoint (``snapshots`` > 0).
        self._last_snapshot = (0, 0, 0.0)
        self.monitor: RunMonitor | None = None  # the run's logs; its state goes into each checkpoint
        # Whether the run has a folder its checkpoints go to (rank 0 alone writes them under torchrun,
        # whose other ranks have no run_dir), and the counters of the last checkpoint there.
        self.has_run_folder = run_dir is not None
        self.saved: dict[str, int] | None = None

    # -- what a trainer supplies -----------------------------------------------------------------
    @abc.abstractmethod
    def _setup(self, resume: dict | None) -> None:
        """Build the model, optimizer and environments; restore ``resume`` (a loaded checkpoint)."""

    @abc.abstractmethod
    def _train_step(self, stop_requested: bool) -> bool:
        """One unit of work, counted with :meth:`_count`; True to stop (a graceful stop, agreed
        wherever the trainer has several processes to agree with)."""

    def _rng_states(self) -> tuple[list[dict], int]:
        """The random streams a checkpoint keeps (one per rank) and the number of ranks."""
        return [], 1

    def _start(self) -> None:
        """Start what runs beside the loop (the Hogwild workers); nothing by default."""
        return

    def _end(self) -> None:
        """Stop what :meth:`_start` started; called once the loop ends and again on the way out."""
        return

    # -- the shared part -------------------------------------------------------------------------
    def _out_of_time(self) -> bool:
        """The wall-clock budget is spent, by this process's clock."""
        cfg = self.config
        return cfg.max_seconds > 0 and time.perf_counter() - self._clock >= cfg.max_seconds

    def _budget_reached(self) -> bool:
        cfg = self.config
        return (
            (cfg.episodes > 0 and self.counters["episodes"] >= cfg.episodes)
            or (cfg.frames > 0 and self.counters["frames"] >= cfg.frames)
            or self._out_of_time()
        )

    def _checkpoint(self, final: bool = False, snapshot: bool = True) -> None:
        rngs, world_size = self._rng_states()  # may be collective: every rank gets here
        if self.run_dir is not None:
            ckpt.save_run_state(
                self.run_dir,
                self.model,
                self.optimizer,
                self.config,
                self.counters,
                rngs,
                world_size,
                final,
                snapshot,
                self.monitor.state() if self.monitor is not None else None,
            )
        if self.has_run_folder:
            self.saved = dict(self.counters)

    def _restore_run_state(self, state: dict) -> None:
        """Read back what :meth:`_checkpoint` wrote of the model, the optimizer and the counters
        (``state``: a loaded checkpoint); each trainer restores its own random streams."""
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.counters = {k: int(v) for k, v in state["counters"].items() if k in self.counters}

    def _check_finite(self, grad_norm: float) -> None:
        """The divergence rule (:func:`~mapless.train.gradients.check_finite`) at this run's counters."""
        check_finite(grad_norm, self.counters, self.saved)

    def _count(self, episodes: int, frames: int, stop_requested: bool = False) -> bool:
        """Advance the counters by one update's episodes and frames (over all ranks), log, and
        checkpoint on schedule. Returns True to stop (the checkpoint is then the caller's)."""
        assert self.monitor is not None, "_count runs inside run()"
        before = self.counters["episodes"]
        self.counters["episodes"] += episodes
        self.counters["frames"] += frames
        self.counters["updates"] += 1
        self.monitor.advance(self.counters["episodes"], self.counters["frames"])
        self._snapshot_due = self._crossed_checkpoint(before)
        if stop_requested:
            return True
        if self._snapshot_due and not self._budget_reached():
            self._checkpoint()
            self._snapshot_due = False
        return False

    def _crossed_checkpoint(self, episodes_before: int) -> bool:
        """Whether the update just counted puts a checkpoint here: every ``checkpoint_every``
        episodes, or with ``snapshots`` a share of the budget since the last one (TrainConfig)."""
        cfg, episodes, frames = self.config, self.counters["episodes"], self.counters["frames"]
        if cfg.snapshots == 0:
            return episodes // cfg.checkpoint_every > episodes_before // cfg.checkpoint_every
        since = (episodes, frames, time.perf_counter() - self._clock)
        budgets = (cfg.episodes, cfg.frames, cfg.max_seconds)
        due = any(
            budget > 0 and now - last >= budget / cfg.snapshots
            for budget, now, last in zip(budgets, since, self._last_snapshot, strict=True)
        )
        if due:
            self._last_snapshot = since
        return due

    def run(self, resume: dict | None = None) -> dict[str, float]:
        """Train until the budget or a graceful stop; ``resume`` is a loaded checkpoint
        (:func:`checkpoint.load_file`). Returns :func:`~mapless.train.monitor.run_summary`."""
        self._setup(resume)
        if resume is not None and self.has_run_folder:
            self.saved = dict(self.counters)  # the checkpoint resumed from
        monitor = self.monitor = RunMonitor.for_run(
            self.run_dir, self.config, self.counters, self.label, resume
        )
        start, start_frames, start_updates = (
            time.perf_counter(),
            self.counters["frames"],
            self.counters["updates"],
        )
        self._clock = start
        # A resumed run's shares of the budget count from here.
        self._last_snapshot = (self.counters["episodes"], self.counters["frames"], 0.0)
        first: tuple[float, int] | None = None  # after the first update (warm-up excluded from steady rates)
        stopped = False
        try:
            self._start()
            with GracefulStop() as stop:
                while not self._budget_reached():
                    stopped = self._train_step(stop.requested)
                    if first is None and self.counters["updates"] > start_updates:
                        first = (time.perf_counter(), self.counters["frames"])
                    if stopped:
                        break
            loop_end = time.perf_counter()
            self._end()
            # A stop writes a snapshot only where the schedule puts one (its update crossed it).
            self._checkpoint(final=not stopped, snapshot=not stopped or self._snapshot_due)
        finally:
            self._end()
            monitor.close(partial_record=not stopped)
        return run_summary(
            self.counters, start, start_frames, first, loop_end, monitor.running_success, stopped
        )
