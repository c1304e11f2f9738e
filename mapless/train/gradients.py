"""What an update does to gradients before the optimizer step: the references' clipping, the
divergence check, and SAVN's zeros for parameters that received none."""

from __future__ import annotations

import numpy as np
import torch

from mapless.errors import TrainingDiverged
from mapless.models import NavModel
from mapless.train.config import TrainConfig


def clip_gradients(model: NavModel, config: TrainConfig) -> float:
    """The references clip non-adaptive models at norm 100 and leave SAVN's meta-gradient alone.
    Returns the gradient's L2 norm before clipping, whether clipping is on or not (it is logged:
    a policy that collapses often does so right after a large step)."""
    limit = config.a3c.meta_grad_clip if model.adaptive else config.a3c.grad_clip
    params = [p for p in model.parameters() if p.grad is not None]
    if not params:
        return 0.0
    norm = torch.nn.utils.get_total_norm([p.grad for p in params])
    if limit > 0:
        torch.nn.utils.clip_grads_with_norm_(params, limit, norm)
    return float(norm)


def check_finite(norm: float, counters: dict[str, int], saved: dict[str, int] | None) -> None:
    """The divergence rule of every trainer (batched A3C, PPO, each Hogwild worker, each torchrun rank
    on the all-reduced gradient): a NaN or infinite gradient norm stops the run before the optimizer
    step would spread it into the parameters. ``counters`` say where the run is; ``saved`` are the
    counters of the last checkpoint written (None: there is none), which the message names as what is
    left, so that it never promises a checkpoint the run did not write."""
    if np.isfinite(norm):
        return
    where = (
        f"the gradient became {norm} at update {counters['updates'] + 1} "
        f"({counters['episodes']} episodes, {counters['frames']} frames): training diverged"
    )
    advice = "lower the learning rate, or check the reward and loss settings"
    if saved is None:
        raise TrainingDiverged(
            f"{where} before the run wrote its first checkpoint, so there is nothing to resume ({advice}, "
            "then start the run again)"
        )
    raise TrainingDiverged(
        f"{where}; the run folder's checkpoint.pt still holds the last good state, at {saved['episodes']} "
        f"episodes ({advice} before resuming)"
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
