"""Graph-prior baselines: ``sp`` (Scene Priors, Yang et al. 2018, as in SAVN's ``GCN``) and ``gve``
(graph-based value estimation, Moghaddam et al.; reconstructed, see docs/guide/models.md).

The graph branch follows SAVN's ``models/gcn.py``: node features ``[class embedding || word
embedding]`` (512 + 512) through three propagation layers ``X <- ReLU(W (Â X))`` (1024 -> 1024 ->
1024 -> 1, no bias), flattened and mapped to 512. The original class embedding is Linear(1000 -> 512)
of ResNet-18's ImageNet class scores, broadcast to every node; the simulator has no ImageNet scores,
so the per-category in-view indicator (``context[..., 0]``, C values) takes their place.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import Knowledge
from mapless.models.a3c import BASE_EMBEDDING, SAVN_EMBEDDING_ROLES, SavnEmbeddingMixin
from mapless.models.base import ModelConfig, RecurrentNavModel
from mapless.models.initialisation import normalized_column_init
from mapless.models.layers import (
    gcn_layer,
    normalized_adjacency_parameter,
    shared_gcn_term,
    shared_row_gcn_layer,
)
from mapless.models.learned_loss import LEARNED_LOSS_ROLES, LearnedLossMixin
from mapless.models.roles import ParameterRoles
from mapless.models.settings import ADAPTIVE, GRAPH, RECURRENT, SAVN_EMBEDDING

GRAPH_EMBEDDING = 512


class ScenePriorsGraph(nn.Module):
    """SAVN's GCN branch over the category set: in-view indicator ``[B, C]`` -> graph embedding ``[B, 512]``."""

    def __init__(self, adjacency, glove, num_categories: int):
        super().__init__()
        self.A = normalized_adjacency_parameter(adjacency)  # trainable, as in SAVN
        self.register_buffer("all_glove", torch.tensor(glove, dtype=torch.float32))
        self.get_class_embed = nn.Linear(num_categories, 512)
        self.get_word_embed = nn.Linear(self.all_glove.shape[1], 512)
        self.W0 = nn.Linear(1024, 1024, bias=False)
        self.W1 = nn.Linear(1024, 1024, bias=False)
        self.W2 = nn.Linear(1024, 1, bias=False)
        self.final_mapping = nn.Linear(num_categories, GRAPH_EMBEDDING)

    def shared_term(self) -> Tensor:
        """The first layer's batch-independent term (:func:`shared_gcn_term`), from the parameters."""
        return shared_gcn_term(self.A, self.get_word_embed(self.all_glove), self.W0)

    def forward(self, in_view: Tensor, shared: Tensor | None = None) -> Tensor:
        """``shared``: :meth:`shared_term`, when the caller keeps it across batches."""
        # Node features [class embedding (the same for every node) || word embedding of the node].
        class_embed = self.get_class_embed(in_view)
        shared = self.shared_term() if shared is None else shared
        x = F.relu(shared_row_gcn_layer(self.A, class_embed, shared, self.W0), inplace=True)  # [C, B, 1024]
        x = F.relu(gcn_layer(self.A, x, self.W1))
        x = F.relu(gcn_layer(self.A, x, self.W2))  # [C, B, 1]
        return self.final_mapping(x.squeeze(-1).T)


class ScenePriorsModel(SavnEmbeddingMixin, RecurrentNavModel):
    description = "Scene Priors: a3c embedding || GCN graph embedding -> LSTM(3648)"
    default_graph = "vg"
    parameter_roles = SAVN_EMBEDDING_ROLES | ParameterRoles(encoder=("graph",))
    settings = RECURRENT | SAVN_EMBEDDING | GRAPH

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_base_embedding()
        self.graph = ScenePriorsGraph(
            self.knowledge.graph(self.graph_name()), self.knowledge.glove, self.num_categories
        )
        self._finish_init(BASE_EMBEDDING + GRAPH_EMBEDDING)

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        # The graph sees the observation only through the in-view row: once per distinct row.
        shared = self.fixed_term("graph", self.graph.shared_term)
        graph = self.per_in_view(obs["context"][..., 0], lambda rows: self.graph(rows, shared))
        return torch.cat([self._base_embedding(obs, prev_policy), graph], dim=1), None


class GveModel(LearnedLossMixin, SavnEmbeddingMixin, RecurrentNavModel):
    """SAVN's actor path unchanged; the Scene-Priors graph embedding g enters only the critic,
    ``V = Linear(1024 -> 1)([h || g])`` (a linear head on the concatenation is the additive decomposed
    value W_h h + W_g g + b). Adaptive like SAVN; the inner step cannot reach the graph or critic."""

    description = "GVE: SAVN actor; critic on [h || graph embedding]; SAVN inner loop"
    default_graph = "vg"
    default_inner_lr = 1e-4
    # The graph feeds only the critic, so the learned loss cannot reach it.
    parameter_roles = SAVN_EMBEDDING_ROLES | LEARNED_LOSS_ROLES | ParameterRoles(outer_only=("gve",))
    settings = RECURRENT | SAVN_EMBEDDING | GRAPH | ADAPTIVE

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_base_embedding()
        self.gve = ScenePriorsGraph(
            self.knowledge.graph(self.graph_name()), self.knowledge.glove, self.num_categories
        )
        self._finish_init(BASE_EMBEDDING)
        # Replace the critic by one over [h || g]; SAVN's critic init (normalised columns, std 1.0).
        self.critic_linear = nn.Linear(self.hidden_size + GRAPH_EMBEDDING, 1)
        normalized_column_init(self.critic_linear, 1.0)
        self._build_learned_loss(with_key_linear=True)

    in_view_outside_encoders = True

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        return self._base_embedding(obs, prev_policy), None

    def critic_context(self, obs: dict[str, Tensor]) -> Tensor:
        """The graph embedding g: outer-only, so once over every row of a call, outside the
        per-episode encoders, and, as sp's graph, once per distinct in-view row within a memo."""
        shared = self.fixed_term("gve", self.gve.shared_term)
        return self.per_in_view(obs["context"][..., 0], lambda rows: self.gve(rows, shared))

    def value(self, h: Tensor, critic_input: Tensor | None) -> Tensor:
        return self.critic_linear(torch.cat([h, critic_input], dim=1))
