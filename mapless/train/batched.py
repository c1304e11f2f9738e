"""The batched trainer (the default): B episodes in lockstep, one batched forward per step, one
optimizer step per batch.

Per update::

    episodes = B reference-sampled training episodes (room-type cycle, random scene/start/target)
    trajectory = run_batch(...)            # lockstep to the end of the longest episode (<= 30 steps)
    loss = mean_b A3C(episode b)           # per-episode losses exactly as the reference computes them
    backward (through the batched inner loop for adaptive models), all-reduce over ranks, clip, step

The same code runs on every rank under torchrun (:mod:`mapless.train.distributed`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapless.agent.acting import observation_keys
from mapless.train import distributed as dist
from mapless.train.builders import BuiltinLibrary, LibraryFactory, new_model, training_env, training_sampler
from mapless.train.config import TrainConfig
from mapless.train.gradients import clip_gradients, fill_missing_gradients, trainable
from mapless.train.loop import TrainingLoop
from mapless.train.monitor import RunMonitor
from mapless.train.optim import SharedAdam
from mapless.train.rollout import accumulate_gradients, make_actor, run_batch
from mapless.train.runtime import configure_torch, seed_for

#: Rows of the per-episode statistics exchanged between ranks.
_EPISODE_ROWS = ("success", "spl", "length", "reward")


class BatchedTrainer(TrainingLoop):
    label = "batched"  # the progress bar's name for the trainer

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

    # -- setup -----------------------------------------------------------------------------------
    def _setup(self, resume: dict | None) -> None:
        cfg, rank = self.config, self.ctx.rank
        configure_torch(cfg.threads)
        torch.manual_seed(seed_for(cfg, rank))
        self.rng = np.random.default_rng(seed_for(cfg, 10_000 + rank))
        self.model = new_model(cfg, self.device)
        self.params = trainable(self.model)
        self.actor = make_actor(self.model, first_order=cfg.meta.first_order, precision=cfg.precision)
        self.optimizer = SharedAdam.from_config(self.params, cfg.optim)
        self.obs_keys = observation_keys(self.model)
        library = self.library_factory()
        self.sampler = training_sampler(cfg, library, seed_for(cfg, 20_000 + rank))
        self.env = training_env(cfg, library, cfg.batch_size)
        if resume is not None:
            self._restore(resume)
        else:
            dist.broadcast_parameters(self.params, self.ctx)

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
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.counters = {k: int(v) for k, v in state["counters"].items() if k in self.counters}
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

    def _out_of_time(self) -> bool:
        # Decided in _account, agreed over ranks (clocks differ per rank).
        return self._time_up

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> dict[str, Any]:
        """One batch of episodes and one optimizer step; returns this rank's statistics."""
        cfg = self.config
        episodes = [self.sampler.sample(self.rng) for _ in range(cfg.batch_size)]
        noise = self.rng.random((cfg.batch_size, cfg.env.max_steps))
        self.optimizer.zero_grad(set_to_none=True)
        trajectory = run_batch(self.actor, self.env, episodes, noise, self.obs_keys, self.device)
        losses = accumulate_gradients(self.actor, trajectory, cfg.loss)
        fill_missing_gradients(self.model)
        dist.all_reduce_gradients(self.params, self.ctx)
        grad_norm = clip_gradients(self.model, cfg)
        self._check_finite(grad_norm)
        self.optimizer.step()
        return {"trajectory": trajectory, "losses": losses, "grad_norm": grad_norm}

    def _train_step(self, stop_requested: bool) -> bool:
        assert self.monitor is not None
        return self._account(self.update(), self.monitor, stop_requested)

    def _account(self, result: dict[str, Any], monitor: RunMonitor, stop_requested: bool) -> bool:
        """Merge statistics over ranks, advance counters, log and checkpoint. Returns True to stop."""
        traj, losses = result["trajectory"], result["losses"]
        rows = torch.tensor(
            np.stack([traj.success, traj.spl(), traj.length, traj.total_reward()]), dtype=torch.float64
        )
        rows = dist.all_gather_rows(rows, self.ctx)
        n = traj.logits.shape[1]
        totals = torch.tensor(
            [
                float(losses.total.detach().sum()),
                float(losses.policy.detach().sum()),
                float(losses.value.detach().sum()),
                float(losses.entropy.detach().sum()),
                float(n),
                float(traj.frames),
                float(stop_requested),
                self._out_of_time_here(),
            ],
            dtype=torch.float64,
        )
        totals = dist.all_reduce_sum(totals, self.ctx)
        episodes, frames = int(totals[4]), int(totals[5])
        monitor.add_episodes(*(rows[i].numpy() for i in range(len(_EPISODE_ROWS))))
        monitor.add_losses(
            float(totals[0] / episodes),
            float(totals[1] / episodes),
            float(totals[2] / episodes),
            float(totals[3] / max(frames, 1)),
            grad_norm=result["grad_norm"],  # of the all-reduced gradient: the same on every rank
            count=episodes,
        )
        return self._advance(monitor, episodes, frames, bool(totals[6] > 0), bool(totals[7] > 0))

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
