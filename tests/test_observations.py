"""The observation is declared once (mapless/observations.py), and what is derived from it is what
was written out key by key before: the gym space, the probe's zero batch and the synthetic batches
(drawn from a generator's stream in the same order, so golden captures made from that stream hold).
No other module of mapless/ lists the observation keys again."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces

from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model
from mapless.models.synthetic import synthetic_observations
from mapless.observations import OBSERVATION_KEYS, ObservationSizes, gym_space, synthetic, zeros

PACKAGE = Path(__file__).resolve().parents[1] / "mapless"


def test_the_gym_space_is_the_one_written_out_by_hand() -> None:
    n = 5
    expected = spaces.Dict(
        {
            "context": spaces.Box(0.0, 1.0, (n, 4), np.float32),
            "features": spaces.Box(0.0, 1.0, (n + 3, 7, 7), np.float32),
            "target_embedding": spaces.Box(-np.inf, np.inf, (300,), np.float32),
            "target_index": spaces.Box(-1, n - 1, (1,), np.int64),
            "context_distance": spaces.Box(0.0, np.inf, (n,), np.float32),
        }
    )
    assert gym_space(ObservationSizes(n)) == expected
    assert set(gym_space(ObservationSizes(n))) == set(OBSERVATION_KEYS)


def test_the_zero_batch_has_each_keys_shape_and_dtype() -> None:
    batch = zeros(ObservationSizes(4, feature_channels=9, embedding=16), batch=2)
    assert {k: (tuple(v.shape), v.dtype) for k, v in batch.items()} == {
        "context": ((2, 4, 4), torch.float32),
        "features": ((2, 9, 7, 7), torch.float32),
        "target_embedding": ((2, 16), torch.float32),
        "target_index": ((2,), torch.int64),
        "context_distance": ((2, 4), torch.float32),
    }
    assert all(not v.any() for v in batch.values())


def _written_out(batch_size, knowledge, feature_channels, generator):
    """The synthetic batch as it was written before the declaration existed."""
    c = knowledge.num_categories
    f = feature_channels or c + 3
    in_view = (torch.rand(batch_size, c, generator=generator) < 0.3).float()
    xy = torch.rand(batch_size, c, 2, generator=generator)
    area = torch.rand(batch_size, c, 1, generator=generator) * 0.2
    context = torch.cat([in_view.unsqueeze(-1), xy, area], dim=-1) * in_view.unsqueeze(-1)
    features = torch.rand(batch_size, f, 7, 7, generator=generator)
    target_index = torch.randint(0, c, (batch_size,), generator=generator)
    distance = (4.5 - 20.0 * area.squeeze(-1)) * in_view
    glove = torch.tensor(knowledge.glove, dtype=torch.float32)
    return {
        "context": context,
        "features": features,
        "target_embedding": glove[target_index].clone(),
        "target_index": target_index,
        "context_distance": distance,
    }


@pytest.mark.parametrize("feature_channels", [None, 11])
def test_the_synthetic_batch_draws_the_same_stream_as_before(feature_channels) -> None:
    knowledge = synthetic_knowledge(6, 300, seed=2)
    new = synthetic_observations(4, knowledge, feature_channels, torch.Generator().manual_seed(5))
    old = _written_out(4, knowledge, feature_channels, torch.Generator().manual_seed(5))
    assert list(new) == list(old) == list(OBSERVATION_KEYS)
    for key in old:
        assert new[key].dtype == old[key].dtype and torch.equal(new[key], old[key]), key


def test_every_synthetic_row_lies_in_the_gym_space() -> None:
    knowledge = synthetic_knowledge(6, 300, seed=0)
    sizes = ObservationSizes(6)
    space = gym_space(sizes)
    batch = synthetic(sizes, knowledge.glove, 8, torch.Generator().manual_seed(0))
    assert batch["context"][..., 0].any()  # some categories in view: the bounds are exercised
    for row in range(8):
        observation = {k: v[row].numpy().reshape(space[k].shape) for k, v in batch.items()}
        assert space.contains(observation), row


def test_the_probe_finds_the_keys_each_model_reads() -> None:
    from mapless.agent.acting import observation_keys

    knowledge = synthetic_knowledge(5, 300, seed=1)
    cvmeta = build_model("cvmeta", knowledge=knowledge, hidden_size=16)
    a3c = build_model("a3c", knowledge=knowledge, hidden_size=16)
    # cvmeta sees the scene through context vectors and the graph, not the feature map (its
    # semantic_map setting off); a3c reads the feature map and the target's GloVe vector.
    assert "features" not in observation_keys(cvmeta) and "context" in observation_keys(cvmeta)
    assert {"features", "target_embedding"} <= set(observation_keys(a3c))
    assert set(observation_keys(a3c)) <= set(OBSERVATION_KEYS)
    # gve's graph is a critic context, read outside encode: the probe still sees its in-view row.
    gve = build_model("gve", knowledge=knowledge, hidden_size=16)
    assert {"features", "context", "target_embedding"} <= set(observation_keys(gve))


def _listings(tree: ast.AST) -> list[int]:
    """Lines of the literals that name three or more observation keys: a tuple, list or set of them,
    a dict with them as keys, or a call with them as keyword arguments. (A scene stores two arrays
    under the names of the keys computed from them, ``context`` and ``features``.)"""
    keys = set(OBSERVATION_KEYS)

    def named(nodes) -> int:
        return sum(isinstance(n, ast.Constant) and n.value in keys for n in nodes)

    lines = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            count = named(node.elts)
        elif isinstance(node, ast.Dict):
            count = named([k for k in node.keys if k is not None])
        elif isinstance(node, ast.Call):
            count = sum(k.arg in keys for k in node.keywords)
        else:
            continue
        if count >= 3:
            lines.append(node.lineno)
    return lines


def test_no_module_but_the_declaration_lists_the_observation_keys() -> None:
    found = {
        path.relative_to(PACKAGE).as_posix(): lines
        for path in PACKAGE.rglob("*.py")
        if (lines := _listings(ast.parse(path.read_text())))
    }
    assert found == {}, found
    # The check sees a listing: the hand-written space above is one.
    assert _listings(ast.parse(Path(__file__).read_text()))
