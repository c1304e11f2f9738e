"""Random observations that satisfy docs/guide/simulator.md, "Observations", for tests, smoke runs and benchmarks."""

from __future__ import annotations

import torch
from torch import Tensor

from mapless.knowledge import Knowledge


def synthetic_observations(
    batch_size: int,
    knowledge: Knowledge,
    feature_channels: int | None = None,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """A batch of plausible observations: a random subset of categories in view with boxes inside the
    frame, a feature map of cell fractions, and a target drawn from the categories."""
    c = knowledge.num_categories
    f = feature_channels or c + 3
    in_view = (torch.rand(batch_size, c, generator=generator) < 0.3).float()
    xy = torch.rand(batch_size, c, 2, generator=generator)
    area = torch.rand(batch_size, c, 1, generator=generator) * 0.2
    context = torch.cat([in_view.unsqueeze(-1), xy, area], dim=-1) * in_view.unsqueeze(-1)
    features = torch.rand(batch_size, f, 7, 7, generator=generator)
    target_index = torch.randint(0, c, (batch_size,), generator=generator)
    # From the box area, not a draw of its own: a caller's generator (and every golden capture made
    # from its stream) goes on as before the distance existed. Larger boxes are nearer, 0.5-4.5 m.
    distance = (4.5 - 20.0 * area.squeeze(-1)) * in_view
    glove = torch.tensor(knowledge.glove, dtype=torch.float32)
    return {
        "context": context,
        "features": features,
        "target_embedding": glove[target_index].clone(),
        "target_index": target_index,
        "context_distance": distance,
    }
