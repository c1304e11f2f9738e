"""The shared base of the two synchronous trainers, PPO (:mod:`mapless.train.ppo`) and the references'
batched A3C (:mod:`mapless.train.batched`): siblings that differ only in what they build beside the
model and in one update.

Both run the same code on every rank under torchrun (:mod:`mapless.train.distributed`); the base
holds what they share: the rank's device and seeds, the model, its observation keys, the training
scenes, sampler and batched environment (:meth:`SynchronousTrainer.build`), the random streams a
checkpoint keeps, and counting an update's totals over ranks. The run loop, budget, checkpoints,
monitor and graceful stop are :class:`~mapless.train.loop.TrainingLoop`'s.
"""

from __future__ import annotations

import abc
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapless.agent.acting import observation_keys
from mapless.train import distributed as dist
from mapless.train.builders import BuiltinLibrary, LibraryFactory, new_model, training_env, training_sampler
from mapless.train.config import TrainConfig
from mapless.train.gradients import trainable
from mapless.train.loop import TrainingLoop
from mapless.train.monitor import RunMonitor
from mapless.train.runtime import configure_torch, seed_for


class SynchronousTrainer(TrainingLoop, abc.ABC):
    """One update at a time on every rank: :meth:`build`, then :meth:`update` until the budget."""

    def __init__(
        self,
        config: TrainConfig,
        run_dir: Path | None,
        library_factory: LibraryFactory | None = None,
        ctx: dist.DistContext | None = None,
    ):
        """``run_dir`` receives logs and checkpoints (rank 0 only); ``library_factory`` defaults to the
        cached built-in scenes (tests pass small hand-made ones)."""
        self.ctx = ctx or dist.DistContext()
        super().__init__(config, run_dir if self.ctx.is_main else None)
        self.has_run_folder = run_dir is not None  # rank 0 writes the checkpoints of every rank
        self.library_factory = library_factory or BuiltinLibrary(config)
        self.device = dist.rank_device(config.device, self.ctx.local_rank)
        self._time_up = False  # the wall-clock limit, as last agreed over ranks

    # -- what an algorithm supplies ----------------------------------------------------------------
    @abc.abstractmethod
    def _environment_slots(self) -> int:
        """How many episodes the batched environment steps side by side."""

    @abc.abstractmethod
    def _build_algorithm(self) -> None:
        """What the algorithm adds to the model and environment: its optimizer and its actor."""

    @abc.abstractmethod
    def update(self) -> dict[str, Any]:
        """One update on this rank (collection, loss, optimizer step); returns its statistics."""

    @abc.abstractmethod
    def _account(self, result: dict[str, Any], monitor: RunMonitor, stop_requested: bool) -> bool:
        """Merge :meth:`update`'s statistics over ranks, then :meth:`_advance`. Returns True to stop."""

    # -- setup -----------------------------------------------------------------------------------
    def build(self, resume: dict | None = None) -> None:
        """Build everything an update needs on this rank: seeds, model, environment and the
        algorithm's parts; then restore ``resume`` (a loaded checkpoint) or, for a fresh run, give
        every rank rank 0's parameters. :meth:`run` calls it; benchmarks and tests call it to step
        updates themselves."""
        cfg, rank = self.config, self.ctx.rank
        configure_torch(cfg.threads)
        torch.manual_seed(seed_for(cfg, rank))
        self.rng = np.random.default_rng(seed_for(cfg, 10_000 + rank))
        self.model = new_model(cfg, self.device)
        self.params = trainable(self.model)
        self.obs_keys = observation_keys(self.model)
        library = self.library_factory()
        self.sampler = training_sampler(cfg, library, seed_for(cfg, 20_000 + rank))
        self.env = training_env(cfg, library, self._environment_slots())
        self._build_algorithm()
        if resume is not None:
            self._restore(resume)
        else:
            dist.broadcast_parameters(self.params, self.ctx)

    def _setup(self, resume: dict | None) -> None:
        self.build(resume)

    # -- random streams ----------------------------------------------------------------------------
    def _rng_state(self) -> dict:
        state = {
            "torch": torch.get_rng_state(),
            "numpy": self.rng.bit_generator.state,
            # The sampler's position in its room-type cycle (its only mutable state).
            "sampler_next_room": self.sampler.position,
        }
        if self.device.type == "cuda":
            state["cuda"] = torch.cuda.get_rng_state(self.device).cpu()
        return state

    def _restore(self, state: dict) -> None:
        self._restore_run_state(state)
        rngs = state.get("rng", [])
        if self.ctx.rank < len(rngs):
            rng = rngs[self.ctx.rank]
            torch.set_rng_state(rng["torch"])
            self.rng.bit_generator.state = rng["numpy"]
            self.sampler.position = int(rng["sampler_next_room"])
            if "cuda" in rng and self.device.type == "cuda":
                torch.cuda.set_rng_state(rng["cuda"], self.device)
        else:
            # More ranks than when the checkpoint was written: fresh, distinct streams for the new ones.
            streams = (self.ctx.rank, self.counters["episodes"])
            torch.manual_seed(seed_for(self.config, 30_000, *streams))
            self.rng = np.random.default_rng(seed_for(self.config, 30_001, *streams))

    def _rng_states(self) -> tuple[list[dict], int]:
        return dist.gather_objects(self._rng_state(), self.ctx), self.ctx.world_size  # collective

    # -- counting ----------------------------------------------------------------------------------
    def _out_of_time(self) -> bool:
        # Decided in _account, agreed over ranks (clocks differ per rank).
        return self._time_up

    def _train_step(self, stop_requested: bool) -> bool:
        assert self.monitor is not None
        return self._account(self.update(), self.monitor, stop_requested)

    def _out_of_time_here(self) -> float:
        """1.0 when this rank's clock passed ``max_seconds`` (agreed over ranks by the caller)."""
        return float(super()._out_of_time())

    def _advance(
        self, monitor: RunMonitor, episodes: int, frames: int, stop_requested: bool, out_of_time: bool
    ) -> bool:
        """Count an update's totals over all ranks (``monitor`` is the run's, ``self.monitor``) with
        the wall-clock verdict agreed over them. Returns True to stop."""
        if not stop_requested:
            self._time_up = out_of_time
        return self._count(episodes, frames, stop_requested)
