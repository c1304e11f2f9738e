"""The batched trainer (the default): B episodes in lockstep, one batched forward per step, one
optimizer step per batch.

Per update::

    episodes = B reference-sampled training episodes (room-type cycle, random scene/start/target)
    trajectory = run_batch(...)            # lockstep to the end of the longest episode (<= 30 steps)
    loss = mean_b A3C(episode b)           # per-episode losses exactly as the reference computes them
    backward (through the batched inner loop for adaptive models), all-reduce over ranks, clip, step

The same code runs on every rank under torchrun (:mod:`mapless.train.distributed`). PPO is its
sibling on the same base (:class:`~mapless.train.synchronous.SynchronousTrainer`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mapless.train import distributed as dist
from mapless.train.gradients import clip_gradients, fill_missing_gradients
from mapless.train.monitor import RunMonitor
from mapless.train.optim import SharedAdam
from mapless.train.rollout import accumulate_gradients, make_actor, run_batch
from mapless.train.synchronous import SynchronousTrainer

#: Rows of the per-episode statistics exchanged between ranks.
_EPISODE_ROWS = ("success", "spl", "length", "reward")


class BatchedTrainer(SynchronousTrainer):
    label = "batched"  # the progress bar's name for the trainer

    def _environment_slots(self) -> int:
        return self.config.a3c.batch_size

    def _build_algorithm(self) -> None:
        cfg = self.config
        self.actor = make_actor(self.model, first_order=cfg.meta.first_order, precision=cfg.a3c.precision)
        self.optimizer = SharedAdam.from_config(self.params, cfg.a3c)

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> dict[str, Any]:
        """One batch of episodes and one optimizer step; returns this rank's statistics."""
        cfg = self.config
        episodes = [self.sampler.sample(self.rng) for _ in range(cfg.a3c.batch_size)]
        noise = self.rng.random((cfg.a3c.batch_size, cfg.env.max_steps))
        self.optimizer.zero_grad(set_to_none=True)
        trajectory = run_batch(self.actor, self.env, episodes, noise, self.obs_keys, self.device)
        losses = accumulate_gradients(self.actor, trajectory, cfg.a3c)
        fill_missing_gradients(self.model)
        dist.all_reduce_gradients(self.params, self.ctx)
        grad_norm = clip_gradients(self.model, cfg)
        self._check_finite(grad_norm)
        self.optimizer.step()
        return {"trajectory": trajectory, "losses": losses, "grad_norm": grad_norm}

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
