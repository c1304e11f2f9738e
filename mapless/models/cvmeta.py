"""The paper's model (Li et al. 2023): context vectors + hierarchical knowledge graph + target word
embedding, fused by pointwise convolution, LSTM(512), actor/critic, SAVN-style meta-learning.

Per category j (the C graph nodes play the role of SAVN's 49 cells):

* context descriptor: ``ReLU(Conv1d 5 -> 64)`` of ``C_j = [B, x_c, y_c, A_bbox, CS]``, dropout;
* graph descriptor: MJOLNIR's object GCN on the *hierarchical* graph, node features
  ``[in-view indicator of all categories || node GloVe]`` (C + 300) through
  ``ReLU(W0 Â ·)``, ``ReLU(W1 Â ·)`` (C + 300 wide, or ``model.gcn_hidden``) and ``ReLU(W2 Â ·)``
  (64 per node);
* target descriptor: ``ReLU(Linear 300 -> 64)`` of the target GloVe, tiled over the categories;
* previous policy: ``ReLU(Linear 6 -> 10)``, tiled (as SAVN).

Their concatenation (202 channels x C) goes through a pointwise ``Conv1d(202 -> fusion_channels)`` +
ReLU + dropout, is flattened (32 x 101 = 3232 by default, close to SAVN's 3136) and enters
LSTMCell(., 512) (with ``model.semantic_map``, not in the paper, the 7x7 feature map's 1x1 embedding
joins the LSTM input). The concatenation is never formed: the convolution is computed part by part, the
tiled vectors' parts once per episode (:func:`~mapless.models.layers.pointwise_conv_of_parts`).
Choices the paper leaves open are argued in docs/guide/models.md.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.profiler import record_function

from mapless.knowledge import Knowledge
from mapless.models.base import (
    EMBED,
    GRID,
    NUM_ACTIONS,
    RECURRENT_CORE_ROLES,
    ModelConfig,
    RecurrentNavModel,
)
from mapless.models.dropout import Dropout
from mapless.models.layers import (
    context_vector,
    gcn_layer,
    normalized_adjacency_parameter,
    pointwise_conv,
    pointwise_conv_of_parts,
    shared_gcn_term,
    shared_row_gcn_layer,
    target_context_input,
)
from mapless.models.learned_loss import LEARNED_LOSS_ROLES, LearnedLossMixin
from mapless.models.roles import ParameterRoles
from mapless.models.settings import ADAPTIVE, GRAPH, RECURRENT

#: Channels of the optional semantic-map embedding (``model.semantic_map``), 16 x 49 LSTM inputs.
SEMANTIC_MAP_CHANNELS = 16


class ContextVectorMetaModel(LearnedLossMixin, RecurrentNavModel):
    description = (
        "the paper's model: context vector + hierarchical GCN + GloVe, pointwise fusion, meta-learning"
    )
    trains_with_parent_reward = True  # the paper trains with the hierarchical parent reward
    default_graph = "hierarchical"
    default_inner_lr = 1e-3  # the paper: "an inner learning rate of 0.001"
    # The paper's meta-objective (eq. 3) adapts θ of a_t ~ π(φ(s_t; v), ψ(g; u); θ), not the encoders.
    default_adapt = "policy"
    parameter_roles = (
        RECURRENT_CORE_ROLES
        | LEARNED_LOSS_ROLES
        | ParameterRoles(
            encoder=(
                "context_embed",
                "A",
                "W0",
                "W1",
                "W2",
                "embed_glove",
                "embed_target_context",
                "embed_map",
            ),
            policy=("embed_action", "pointwise"),
        )
    )
    # Its own context rows gain the distance with or without the target row.
    settings = (
        RECURRENT
        | GRAPH
        | ADAPTIVE
        | {
            "dropout": "",
            "target_context": "",
            "context_distance": "",
            "fusion_channels": "",
            "gcn_hidden": "",
            "semantic_map": "",
        }
    )

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        nodes, width = self.num_categories, self.num_categories + self.glove_dim
        hidden = config.gcn_hidden or width
        distance = int(config.context_distance)
        self.context_embed = nn.Conv1d(5 + distance, EMBED, 1)
        self.A = normalized_adjacency_parameter(self.knowledge.graph(self.graph_name()))
        self.register_buffer("all_glove", torch.tensor(self.knowledge.glove, dtype=torch.float32))
        self.W0 = nn.Linear(width, hidden, bias=False)
        self.W1 = nn.Linear(hidden, hidden, bias=False)
        self.W2 = nn.Linear(hidden, EMBED, bias=False)
        self.embed_glove = nn.Linear(self.glove_dim, EMBED)
        if config.target_context:
            self.embed_target_context = nn.Linear(4 + distance, EMBED)
        self.embed_action = nn.Linear(NUM_ACTIONS, 10)
        self.pointwise = nn.Conv1d(EMBED + EMBED + EMBED + 10, config.fusion_channels, 1)
        self.dropout = Dropout(config.dropout)
        map_width = 0
        if config.semantic_map:
            self.embed_map = nn.Conv2d(self.feature_channels, SEMANTIC_MAP_CHANNELS, 1)
            map_width = SEMANTIC_MAP_CHANNELS * GRID * GRID
        self.build_recurrent_core(config.fusion_channels * nodes + map_width)
        self._build_learned_loss(with_key_linear=False)

    def graph_descriptor(self, in_view: Tensor) -> Tensor:
        """Hierarchical GCN, in-view indicator ``[B, C]`` -> per-node embedding ``[B, 64, C]``."""
        with record_function("graph"):
            return self.per_in_view(in_view, self._hierarchical_gcn)

    def _hierarchical_gcn(self, in_view: Tensor) -> Tensor:
        shared = self.fixed_term("gcn", lambda: shared_gcn_term(self.A, self.all_glove, self.W0))
        x = F.relu(shared_row_gcn_layer(self.A, in_view, shared, self.W0), inplace=True)  # [C, B, hidden]
        x = F.relu(gcn_layer(self.A, x, self.W1))
        x = F.relu(gcn_layer(self.A, x, self.W2))  # [C, B, 64]
        return x.permute(1, 2, 0)

    def describe(self, obs: dict[str, Tensor]) -> dict[str, Tensor]:
        """Context and graph descriptors ``[B, 64, C]`` and the target descriptor ``[B, 64]``."""
        cv = context_vector(obs, self.all_glove, self.config.context_distance)  # [B, C, 5 or 6]
        context = self.dropout(F.relu(pointwise_conv(self.context_embed, cv.transpose(1, 2))))
        graph = self.graph_descriptor(obs["context"][..., 0])
        target = self.embed_glove(obs["target_embedding"])
        if self.config.target_context:
            target = target + target_context_input(
                obs, self.embed_target_context, self.config.context_distance
            )
        target = F.relu(target)
        described = {"context": context, "graph": graph, "target": target}
        if self.config.semantic_map:
            semantic_map = F.relu(pointwise_conv(self.embed_map, obs["features"]))
            described["map"] = self.dropout(semantic_map).flatten(1)
        return described

    def encode(
        self, described: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        action = F.relu(self.embed_action(prev_policy))
        maps = [described["context"], described["graph"]]
        fused = F.relu(pointwise_conv_of_parts(self.pointwise, maps, [described["target"], action]))
        x = self.dropout(fused).flatten(1)
        if self.config.semantic_map:
            x = torch.cat([x, described["map"]], dim=1)
        return x, None
