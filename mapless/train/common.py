"""Pieces both trainers build the same way: scenes, targets, sampler, model, gradient clipping."""

from __future__ import annotations

import contextlib
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapless.agent.precision import keep_compiled_kernels
from mapless.episodes.sampler import TrainingSampler
from mapless.errors import TrainingDiverged
from mapless.models import NavModel, build_model
from mapless.offline import offline_library
from mapless.sim.library import SceneLibrary
from mapless.sim.task import RewardConfig, TargetFields
from mapless.sim.vector import BatchedNavEnv
from mapless.train.config import TrainConfig

#: Builds the scene library in the process that needs it (async workers build their own).
LibraryFactory = Callable[[], SceneLibrary]


@dataclass(frozen=True)
class BuiltinLibrary:
    """Picklable factory of the run's scenes: the cached built-in ones, or an offline data root."""

    config: TrainConfig

    def __call__(self) -> SceneLibrary:
        env = self.config.env
        if env.offline_dir:
            return offline_library(env.offline_dir, env.sim.category_set)
        return SceneLibrary.builtin(env.sim, Path(env.cache_dir) if env.cache_dir else None)


def prepare_scenes(config: TrainConfig) -> None:
    """Build the run's missing scene caches up front, in parallel and with a progress bar."""
    BuiltinLibrary(config)().prepare(config.env.scene_list(), progress=config.progress)


def target_fields(config: TrainConfig) -> TargetFields:
    """GloVe target embeddings and (for the parent reward) parent tables of the run's category set."""
    return TargetFields(config.model.category_set)


def reward_config(config: TrainConfig) -> RewardConfig:
    env = config.env
    return RewardConfig(
        step_penalty=env.step_penalty,
        success_reward=env.success_reward,
        parent_reward=config.parent_reward,
        parent_reward_rooms=env.parent_reward_rooms,
    )


def training_sampler(config: TrainConfig, library: SceneLibrary, seed: int) -> TrainingSampler:
    return TrainingSampler(library, config.env.scene_list(), config.env.target_set, seed=seed)


def training_env(config: TrainConfig, library: SceneLibrary, batch_size: int) -> BatchedNavEnv:
    """``batch_size`` training episodes in lockstep on the run's scenes, targets and rewards."""
    return BatchedNavEnv(
        library,
        config.env.scene_list(),
        batch_size,
        targets=target_fields(config),
        rewards=reward_config(config),
        mode="train",
        max_steps=config.env.max_steps,
    )


def configure_torch(threads: int) -> None:
    """Per-process torch settings of a trainer: ``threads`` (0 = torch's default), denormals
    flushed to zero, and oneDNN's compiled kernels kept (:func:`keep_compiled_kernels`).

    Adam's second-moment estimate of weights that rarely receive gradient (the LSTM columns of
    mostly-zero ReLU features) decays into the subnormal range, where every multiply and square root
    takes the CPU's slow microcode path: a third of a SAVN optimizer step in profiles. Values below
    1.2e-38 are zero for all purposes here.
    """
    if threads:
        torch.set_num_threads(threads)
    torch.set_flush_denormal(True)
    keep_compiled_kernels()


def new_model(config: TrainConfig, device: torch.device | str = "cpu") -> NavModel:
    return build_model(config.model).to(device).train()


def clip_gradients(model: NavModel, config: TrainConfig) -> float:
    """The references clip non-adaptive models at norm 100 and leave SAVN's meta-gradient alone.
    Returns the gradient's L2 norm before clipping, whether clipping is on or not (it is logged:
    a policy that collapses often does so right after a large step)."""
    limit = config.optim.meta_grad_clip if model.adaptive else config.optim.grad_clip
    params = [p for p in model.parameters() if p.grad is not None]
    if not params:
        return 0.0
    norm = torch.nn.utils.get_total_norm([p.grad for p in params])
    if limit > 0:
        torch.nn.utils.clip_grads_with_norm_(params, limit, norm)
    return float(norm)


def check_finite(norm: float, counters: dict[str, int]) -> None:
    """Stop a run whose gradient is NaN or infinite, before the optimizer step spreads it."""
    if not np.isfinite(norm):
        raise TrainingDiverged(
            f"the gradient became {norm} at update {counters['updates'] + 1} "
            f"({counters['episodes']} episodes, {counters['frames']} frames): training diverged; the run "
            "folder's checkpoint.pt still holds the last good state (lower the learning rate, or check the "
            "reward and loss settings, before resuming)"
        )


def trainable(model: NavModel) -> list[torch.Tensor]:
    return [p for p in model.parameters() if p.requires_grad]


def fill_missing_gradients(model: NavModel) -> None:
    """SAVN hands a None gradient to the shared optimizer as zeros (its learned-loss parameters get
    none in an episode without inner step), so Adam's moments still decay; the non-adaptive
    references skip such parameters, which is what None already does."""
    if model.adaptive:
        for p in trainable(model):
            if p.grad is None:
                p.grad = torch.zeros_like(p)


def seed_for(config: TrainConfig, *stream: int) -> int:
    """Independent seeds per rank / worker / resumed segment from one config seed."""
    return int(np.random.SeedSequence([config.seed, *stream]).generate_state(1)[0])


class GracefulStop:
    """First SIGINT or SIGTERM (what schedulers and ``timeout`` send): finish the current update,
    checkpoint and stop. A second one aborts at once."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> GracefulStop:
        for signum in self.SIGNALS:
            # Outside the main thread (e.g. a test harness) there is no handler and no graceful stop.
            with contextlib.suppress(ValueError):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(f"\nmapless: {name}: stopping after this update (again to abort)", flush=True)

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)


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
