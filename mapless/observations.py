"""The observation, declared once below everything that uses it (docs/guide/simulator.md,
"Observations"): every key a model can read, with its dtype, its shape for a category set, its
bounds and how a plausible random value of it is drawn.

Derived from it: the gymnasium observation space (:func:`gym_space`, the gym environment's), the
zero batch a probe forward pass finds a model's keys with (:func:`zeros`,
:func:`mapless.agent.acting.observation_keys`) and the random batches of tests, smoke runs and
benchmarks (:func:`synthetic`). The simulator computes each key
(:meth:`mapless.sim.vector.BatchedNavEnv.observe`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from gymnasium import spaces

GRID = 7  # the feature map's side (ResNet-18's conv5 size)
GLOVE_DIM = 300  # the width of a category's GloVe vector


@dataclass(frozen=True)
class ObservationSizes:
    """The sizes an observation's shapes depend on: the category count ``C``, the feature map's
    channels (None: ``C + 3``, the categories, floor, walls and depth) and the embedding width."""

    categories: int
    feature_channels: int | None = None
    embedding: int = GLOVE_DIM

    @property
    def channels(self) -> int:
        return self.feature_channels or self.categories + 3


class _Draws:
    """The random quantities several keys share (whether a category is in view, its box), each drawn
    once, when a key first reads it. The keys are drawn in :data:`OBSERVATION`'s order, so the
    caller's generator is consumed in a fixed order: in view, box centres, box areas, feature map,
    target. Golden values captured from a generator's stream depend on that order."""

    def __init__(self, batch: int, sizes: ObservationSizes, glove: Tensor, generator: torch.Generator | None):
        self.batch, self.sizes, self.glove, self.generator = batch, sizes, glove, generator

    def rand(self, *shape: int) -> Tensor:
        return torch.rand(self.batch, *shape, generator=self.generator)

    @cached_property
    def in_view(self) -> Tensor:
        return (self.rand(self.sizes.categories) < 0.3).float()

    @cached_property
    def centre(self) -> Tensor:
        return self.rand(self.sizes.categories, 2)

    @cached_property
    def area(self) -> Tensor:
        return self.rand(self.sizes.categories, 1) * 0.2

    @cached_property
    def target(self) -> Tensor:
        c = self.sizes.categories
        return torch.randint(0, c, (self.batch,), generator=self.generator)


@dataclass(frozen=True)
class ObservationKey:
    """One key of the observation dict: what a row holds (``description``), its ``dtype``, its
    ``shape`` per row, its ``bounds`` (low, high) and a plausible random batch of it (``draw``)."""

    name: str
    description: str
    dtype: str  # a numpy and torch dtype name
    shape: Callable[[ObservationSizes], tuple[int, ...]]
    bounds: Callable[[ObservationSizes], tuple[float, float]]
    draw: Callable[[_Draws], Tensor]

    def space_shape(self, sizes: ObservationSizes) -> tuple[int, ...]:
        """The gym space's shape: one element for a scalar, not a 0-d array, because
        stable-baselines3's policies refuse 0-d observations."""
        return self.shape(sizes) or (1,)


def _context(d: _Draws) -> Tensor:
    in_view = d.in_view.unsqueeze(-1)
    return torch.cat([in_view, d.centre, d.area], dim=-1) * in_view


def _distance(d: _Draws) -> Tensor:
    # From the box area, not a draw of its own: a caller's generator (and every golden capture made
    # from its stream) goes on as before the distance existed. Larger boxes are nearer, 0.5-4.5 m.
    return (4.5 - 20.0 * d.area.squeeze(-1)) * d.in_view


#: Every observation key a model can read, in the simulator's order.
OBSERVATION: tuple[ObservationKey, ...] = (
    ObservationKey(
        "context",
        "per category [in view, x_c, y_c, union-box area]",
        "float32",
        lambda s: (s.categories, 4),
        lambda s: (0.0, 1.0),
        _context,
    ),
    ObservationKey(
        "features",
        "the semantic feature map (categories, floor, walls, depth), cell fractions",
        "float32",
        lambda s: (s.channels, GRID, GRID),
        lambda s: (0.0, 1.0),
        lambda d: d.rand(d.sizes.channels, GRID, GRID),
    ),
    ObservationKey(
        "target_embedding",
        "the GloVe vector of the target",
        "float32",
        lambda s: (s.embedding,),
        lambda s: (-np.inf, np.inf),
        lambda d: d.glove[d.target].clone(),
    ),
    ObservationKey(
        "target_index",
        "the target's row in the category set (-1 if none)",
        "int64",
        lambda s: (),
        lambda s: (-1, s.categories - 1),
        lambda d: d.target,
    ),
    ObservationKey(
        "context_distance",
        "per category, the distance (m) to its nearest in-view instance (0 when none is in view)",
        "float32",
        lambda s: (s.categories,),
        lambda s: (0.0, np.inf),
        _distance,
    ),
)
OBSERVATION_KEYS: tuple[str, ...] = tuple(key.name for key in OBSERVATION)


def gym_space(sizes: ObservationSizes) -> spaces.Dict:
    """The gymnasium ``Dict`` space of one observation."""
    from gymnasium import spaces  # only the gym environment needs gymnasium

    return spaces.Dict(
        {
            key.name: spaces.Box(*key.bounds(sizes), key.space_shape(sizes), np.dtype(key.dtype))
            for key in OBSERVATION
        }
    )


def zeros(sizes: ObservationSizes, batch: int = 1) -> dict[str, Tensor]:
    """An all-zero batch of every key."""
    return {
        key.name: torch.zeros(batch, *key.shape(sizes), dtype=getattr(torch, key.dtype))
        for key in OBSERVATION
    }


def synthetic(
    sizes: ObservationSizes, glove: np.ndarray, batch: int, generator: torch.Generator | None = None
) -> dict[str, Tensor]:
    """A batch of plausible observations of every key: a random subset of categories in view with
    boxes inside the frame, a feature map of cell fractions, and a target drawn from the categories
    (``glove [C, embedding]``: its GloVe vectors)."""
    draws = _Draws(batch, sizes, torch.tensor(glove, dtype=torch.float32), generator)
    return {key.name: key.draw(draws) for key in OBSERVATION}
