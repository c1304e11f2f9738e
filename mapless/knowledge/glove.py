"""GloVe vectors of object types, packaged per category set.

``mjolnir101`` uses MJOLNIR's ``glove_thorv1_300`` table (106 AI2-THOR 1.0.1 types: the 101 graph
nodes plus every target); AI2-THOR 5 names that were renamed after v1 resolve to their v1 vector
(``DiningTable``/``CoffeeTable`` -> ``TableTop``, ``SideTable`` -> ``NightStand``, ``Bottle`` ->
``Glassbottle``), the same mapping the category set uses for its rows. ``all_types`` uses the iTHOR-v3
fork's ``glove_thorv3_300`` table, which covers every v5 type. The two tables are different
embeddings and are never mixed (data README caveat 7).
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np

from mapless.errors import UnknownNameError
from mapless.scenes.categories import CATEGORY_SETS, V1_TO_V5, category_set

GLOVE_FILES = {"mjolnir101": "priors/glove_thorv1_300.npz", "all_types": "priors/glove_thorv3_300.npz"}


@functools.cache
def glove_table(category_set_name: str = "mjolnir101") -> dict[str, np.ndarray]:
    """Every packaged vector of the category set's table, keyed by type name (float32, read-only)."""
    if category_set_name not in GLOVE_FILES:
        raise UnknownNameError("category set", category_set_name, CATEGORY_SETS)
    with resources.files("mapless.data").joinpath(GLOVE_FILES[category_set_name]).open("rb") as f:
        data = np.load(f)
        names, vectors = [str(n) for n in data["names"]], data["vectors"].astype(np.float32)
    vectors.setflags(write=False)
    table = dict(zip(names, vectors, strict=True))
    if category_set_name == "mjolnir101":
        # v5 spellings of renamed v1 types share the v1 vector, so a v5 target name always resolves.
        for v1_name, v5_names in V1_TO_V5.items():
            for v5_name in v5_names:
                table.setdefault(v5_name, table[v1_name])
    return table


def glove_vector(type_name: str, category_set_name: str = "mjolnir101") -> np.ndarray:
    """GloVe vector ``[300]`` (float32) of an object type (v1 or v5 spelling) in the set's table."""
    table = glove_table(category_set_name)
    if type_name not in table:
        raise UnknownNameError(f"GloVe type ({category_set_name})", type_name, sorted(table))
    return table[type_name]


@functools.cache
def category_glove(category_set_name: str = "mjolnir101") -> np.ndarray:
    """``[C, 300]`` float32 matrix: row ``i`` is the vector of category ``i`` of the set."""
    names = category_set(category_set_name).names
    matrix = np.stack([glove_vector(n, category_set_name) for n in names])
    matrix.setflags(write=False)
    return matrix
