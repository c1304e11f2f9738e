"""The ``async`` trainer, faithful to SAVN/MJOLNIR: Hogwild A3C with one episode per worker update.

The main process owns a model and a :class:`~mapless.train.optim.SharedAdam` whose tensors live in
shared memory, starts ``workers`` processes (spawn: forking a process whose torch thread pool is
running can deadlock) and then only collects per-episode statistics, logs and checkpoints. Each
worker loops::

    local model <- shared model
    play one episode at batch size 1 (rollout.run_batch, the batched trainer's loop at B = 1)
    backward the episode's A3C loss (through the inner loop for adaptive models)
    clip (non-adaptive models, norm 100), hand the gradients to the shared parameters, optimizer step

without locks, as the references do. A worker whose gradient is NaN or infinite (the divergence
rule of every trainer, :func:`~mapless.train.gradients.check_finite`) reports it instead of
stepping, and the trainer stops the run with the rule's error. A worker that raises or dies (even by SIGKILL) is reported by
rank, pid and exit code, and the run stops: the main process polls the workers' exit codes while it
waits for statistics, so it never blocks on a dead worker.

Resuming restores the model, the optimizer state and the counters; the workers' episode streams are
reseeded from the episode counter (Hogwild updates interleave nondeterministically, so an async run
is not bit-reproducible anyway; the batched trainer is).

The run loop, budget, checkpoints (written and read back), monitor, divergence rule and graceful
stop are :class:`~mapless.train.loop.TrainingLoop`'s, as for PPO and the batched A3C trainer; the
objects a worker builds come from :mod:`mapless.train.builders` and its update from
:mod:`mapless.train.rollout`, as the batched trainer's do. It is not a
:class:`~mapless.train.synchronous.SynchronousTrainer`: its model and optimizer live in shared
memory in the main process, which builds no environment; each worker builds its own and steps
without the ranks' all-reduce, and no random stream is kept in the checkpoint.
"""

from __future__ import annotations

import os
import queue as queue_module
import signal
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp

from mapless.agent.acting import observation_keys
from mapless.errors import MaplessError, TrainingDiverged
from mapless.train.builders import (
    BuiltinLibrary,
    LibraryFactory,
    new_model,
    training_env,
    training_sampler,
)
from mapless.train.config import TrainConfig
from mapless.train.gradients import check_finite, clip_gradients, fill_missing_gradients, trainable
from mapless.train.loop import TrainingLoop
from mapless.train.optim import SharedAdam
from mapless.train.rollout import accumulate_gradients, make_actor, run_batch
from mapless.train.runtime import configure_torch, seed_for

POLL_SECONDS = 0.2
#: A worker applies the divergence rule without the run's counters (the trainer reports them).
_UNCOUNTED = {"updates": 0, "episodes": 0, "frames": 0}
JOIN_SECONDS = 10.0


class WorkerError(MaplessError):
    """A training worker raised or died; the run was stopped."""


def _worker(
    rank: int,
    config: TrainConfig,
    shared_model: torch.nn.Module,
    shared_states: list[dict[str, torch.Tensor]],
    results: Any,
    stop: Any,
    library_factory: LibraryFactory,
    seed: int,
) -> None:
    # Ctrl-C reaches the whole process group; only the main process decides how to stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()
    try:
        configure_torch(threads=1)
        torch.manual_seed(seed)
        rng = np.random.default_rng(seed)
        library = library_factory()
        sampler = training_sampler(config, library, seed)
        env = training_env(config, library, batch_size=1)
        device = torch.device("cpu")
        local = new_model(config)
        actor = make_actor(local, first_order=config.meta.first_order, precision=config.a3c.precision)
        keys = observation_keys(local)
        shared_params, local_params = trainable(shared_model), trainable(local)
        optimizer = SharedAdam.from_config(shared_params, config.a3c)
        for p, state in zip(shared_params, shared_states, strict=True):
            optimizer.state[p] = state  # the shared moments and step counters
        while not stop.is_set():
            if os.getppid() != parent:  # the trainer died (SIGKILL): stop instead of training on as an orphan
                return
            local.load_state_dict(shared_model.state_dict())
            episode = sampler.sample(rng)
            noise = rng.random((1, config.env.max_steps))
            local.zero_grad(set_to_none=True)
            trajectory = run_batch(actor, env, [episode], noise, keys, device)
            losses = accumulate_gradients(actor, trajectory, config.a3c)
            fill_missing_gradients(local)
            grad_norm = clip_gradients(local, config)
            try:
                check_finite(grad_norm, _UNCOUNTED, None)
            except TrainingDiverged:
                # No step: the shared parameters stay finite. The trainer stops the run on this
                # report with the rule's message at its own counters and checkpoint, which the
                # worker does not know.
                results.put(("diverged", rank, grad_norm))
                continue
            for lp, sp in zip(local_params, shared_params, strict=True):
                sp.grad = lp.grad
            optimizer.step()
            results.put(
                (
                    "episode",
                    rank,
                    {
                        "success": float(trajectory.success[0]),
                        "spl": float(trajectory.spl()[0]),
                        "length": int(trajectory.length[0]),
                        "reward": float(trajectory.total_reward()[0]),
                        "total": float(losses.total.detach()[0]),
                        "policy": float(losses.policy.detach()[0]),
                        "value": float(losses.value.detach()[0]),
                        "entropy": float(losses.entropy.detach()[0]),
                        "grad_norm": grad_norm,
                    },
                )
            )
    except BaseException:  # report everything, KeyboardInterrupt included, then exit non-zero
        results.put(("error", rank, traceback.format_exc()))
        raise SystemExit(1) from None


class AsyncTrainer(TrainingLoop):
    label = "async"

    def __init__(
        self, config: TrainConfig, run_dir: Path | None, library_factory: LibraryFactory | None = None
    ):
        if config.device != "cpu":
            raise MaplessError("async mode runs its workers on the CPU; use a3c.mode=batched for device=cuda")
        super().__init__(config, run_dir)
        self.library_factory = library_factory or BuiltinLibrary(config)
        self.workers: list[Any] = []

    def _setup(self, resume: dict | None) -> None:
        cfg = self.config
        configure_torch(cfg.threads)
        torch.manual_seed(seed_for(cfg, 0))
        self.model = new_model(cfg)
        self.optimizer = SharedAdam.from_config(trainable(self.model), cfg.a3c)
        if resume is not None:
            self._restore_run_state(resume)
        self.model.share_memory()
        self.optimizer.share_memory()

    # -- workers ---------------------------------------------------------------------------------
    def _start(self) -> None:
        cfg = self.config
        context = mp.get_context("spawn")
        self.results = context.Queue()
        self.stop = context.Event()
        states = [self.optimizer.state[p] for p in trainable(self.model)]
        segment = self.counters["episodes"]  # a resumed run gets fresh episode streams
        for rank in range(cfg.a3c.workers):
            process = context.Process(
                target=_worker,
                args=(
                    rank,
                    cfg,
                    self.model,
                    states,
                    self.results,
                    self.stop,
                    self.library_factory,
                    seed_for(cfg, 40_000 + rank, segment),
                ),
                name=f"mapless-worker-{rank}",
                daemon=True,
            )
            process.start()
            self.workers.append(process)

    def _check_workers(self) -> None:
        for rank, process in enumerate(self.workers):
            if process.exitcode is not None:
                code = process.exitcode
                how = (
                    f"was killed by signal {signal.Signals(-code).name}"
                    if code < 0
                    else f"exited with code {code}"
                )
                message = f"worker {rank} (pid {process.pid}) {how}; the run was stopped"
                report = self._error_report(rank)
                raise WorkerError(f"{message}:\n{report}" if report else message)

    def _error_report(self, rank: int) -> str | None:
        """The traceback a failed worker sent before exiting, if it is in the queue (the episodes
        queued with it are dropped: the run stops). The other workers keep sending, so the search
        stops at a deadline rather than at an empty queue."""
        deadline = time.monotonic() + 5 * POLL_SECONDS  # a worker's last message precedes its exit
        try:
            while time.monotonic() < deadline:
                kind, sender, payload = self.results.get(timeout=POLL_SECONDS)
                if kind == "error" and sender == rank:
                    return payload
        except (queue_module.Empty, OSError, EOFError):
            pass
        return None

    def _end(self) -> None:
        """Ask the workers to stop, drain their queue so none blocks on a full pipe, then join;
        a worker still alive after the grace period is terminated."""
        if not self.workers:
            return
        self.stop.set()
        deadline = time.monotonic() + JOIN_SECONDS
        while any(p.is_alive() for p in self.workers) and time.monotonic() < deadline:
            try:
                while True:
                    self.results.get_nowait()
            except (queue_module.Empty, OSError, EOFError):
                pass
            time.sleep(0.05)
        for process in self.workers:
            if process.is_alive():
                process.terminate()
            process.join(timeout=JOIN_SECONDS)
            if process.is_alive():
                process.kill()
                process.join()
        self.results.close()
        self.results.cancel_join_thread()
        self.workers = []

    # -- loop ------------------------------------------------------------------------------------
    def _train_step(self, stop_requested: bool) -> bool:
        """Count the next episode a worker finished, if one arrives within the poll interval.
        Scheduled snapshots are written as episodes are counted; a stop adds none."""
        if stop_requested:
            return True
        try:
            kind, rank, payload = self.results.get(timeout=POLL_SECONDS)
        except queue_module.Empty:
            self._check_workers()
            return False
        if kind == "error":
            raise WorkerError(f"worker {rank} failed; the run was stopped:\n{payload}")
        if kind == "diverged":
            self._check_finite(payload)  # raises: the worker's gradient was not finite
        self._account(payload)
        self._check_workers()
        return False

    def _account(self, stats: dict[str, float]) -> None:
        assert self.monitor is not None
        self.monitor.add_episodes(*(np.array([stats[k]]) for k in ("success", "spl", "length", "reward")))
        self.monitor.add_losses(
            stats["total"],
            stats["policy"],
            stats["value"],
            stats["entropy"] / max(stats["length"], 1),
            grad_norm=stats["grad_norm"],
        )
        self._count(1, int(stats["length"]))
