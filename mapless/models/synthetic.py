"""Random observations that satisfy docs/guide/simulator.md, "Observations": a batch to test a model
with (its shapes, gradients, every form of its step) without building a scene."""

from __future__ import annotations

import torch
from torch import Tensor

from mapless.knowledge import Knowledge
from mapless.observations import ObservationSizes, synthetic


def synthetic_observations(
    batch_size: int,
    knowledge: Knowledge,
    feature_channels: int | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """A batch of plausible observations of ``knowledge``'s categories
    (:func:`mapless.observations.synthetic`)."""
    sizes = ObservationSizes(knowledge.num_categories, feature_channels, knowledge.glove_dim)
    return synthetic(sizes, knowledge.glove, batch_size, generator)
