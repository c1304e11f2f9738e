"""Prior knowledge the models and the environment share: GloVe vectors, category graphs, parent objects.

Everything is read from package data (``mapless/data/priors``, provenance in its ``NOTICE.md``).
:class:`Knowledge` bundles what a model needs for one category set; :func:`load_knowledge` builds it
from the packaged data and :func:`synthetic_knowledge` builds a tiny random one for tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapless.knowledge.glove import category_glove, glove_table, glove_vector
from mapless.knowledge.graph import (
    GRAPHS,
    category_graph,
    hierarchical_adjacency,
    normalize_adjacency,
    vg_adjacency,
)
from mapless.knowledge.parents import (
    parent_lists,
    parent_reward,
    parent_reward_by_name,
    parent_weights,
    parents_of,
)
from mapless.scenes.catalogue import ROOM_TYPES
from mapless.scenes.categories import category_set

__all__ = [
    "GRAPHS",
    "Knowledge",
    "category_glove",
    "category_graph",
    "glove_table",
    "glove_vector",
    "hierarchical_adjacency",
    "load_knowledge",
    "normalize_adjacency",
    "parent_lists",
    "parent_reward",
    "parent_reward_by_name",
    "parent_weights",
    "parents_of",
    "synthetic_knowledge",
    "vg_adjacency",
]


@dataclass(frozen=True, eq=False)
class Knowledge:
    """Per-category-set inputs of the models: names, GloVe ``[C, D]`` and 0/1 graphs ``[C, C]``."""

    category_names: tuple[str, ...]
    glove: np.ndarray
    graphs: dict[str, np.ndarray]

    @property
    def num_categories(self) -> int:
        return len(self.category_names)

    @property
    def glove_dim(self) -> int:
        return int(self.glove.shape[1])

    def graph(self, name: str) -> np.ndarray:
        if name not in self.graphs:
            from mapless.errors import UnknownNameError

            raise UnknownNameError("graph", name, self.graphs)
        return self.graphs[name]


def load_knowledge(
    set_name: str = "mjolnir101",
    hierarchy_rooms: tuple[str, ...] = ROOM_TYPES,
    target_set: str | None = None,
) -> Knowledge:
    """Packaged GloVe and graphs of a category set; ``hierarchy_rooms`` selects whose parent edges
    enter, ``target_set`` (a run's) adds its targets' parent edges to the shared ones (graph.py)."""
    return Knowledge(
        category_names=category_set(set_name).names,
        glove=category_glove(set_name),
        graphs={name: category_graph(name, set_name, tuple(hierarchy_rooms), target_set) for name in GRAPHS},
    )


def synthetic_knowledge(num_categories: int = 6, glove_dim: int = 300, seed: int = 0) -> Knowledge:
    """Random GloVe and random symmetric graphs (with self-loops) for tiny tests and smoke runs."""
    rng = np.random.default_rng(seed)
    graphs = {}
    for name in GRAPHS:
        a = rng.random((num_categories, num_categories)) < 0.4
        a = a | a.T
        np.fill_diagonal(a, True)
        graphs[name] = a.astype(np.float32)
    return Knowledge(
        category_names=tuple(f"Category{i}" for i in range(num_categories)),
        glove=rng.standard_normal((num_categories, glove_dim)).astype(np.float32),
        graphs=graphs,
    )
