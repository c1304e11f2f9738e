"""MJOLNIR (Qiu et al. 2020): ``mjolnir_o`` (object-only) and ``mjolnir_r`` (object GCN + SAVN embedding).

Context matrix CM ``[C, 5]`` = the context vector (in view, box centre, union-box area, GloVe cosine
with the target). Object GCN: ``X0 = [in-view indicator repeated per node || node GloVe]``
(C + 300), ``X1 = ReLU(W0 Â X0)``, ``X2 = ReLU(W1 Â X1)`` (C + 300 each), ``X3 = ReLU(W2 Â X2)`` (5),
``X4 = ReLU(W3 Â [X3 || CM])`` (1), flatten, ``final_mapping`` C -> 512. ``mjolnir_o`` feeds
``[CM flattened (5C) || ReLU(Linear 6->10)(previous policy) || GCN (512)]`` (1027 for C = 101) to the
LSTM; ``mjolnir_r`` feeds ``[SAVN embedding (3136) || GCN (512)]`` (3648). Â is trainable.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import Knowledge
from mapless.models.a3c import BASE_EMBEDDING, SAVN_EMBEDDING_ROLES, SavnEmbeddingMixin
from mapless.models.base import NUM_ACTIONS, ModelConfig, RecurrentNavModel
from mapless.models.layers import (
    context_vector,
    gcn_layer,
    normalized_adjacency_parameter,
    shared_gcn_term,
    shared_row_gcn_layer,
    target_row,
)
from mapless.models.roles import ParameterRoles
from mapless.models.settings import GRAPH, RECURRENT, SAVN_EMBEDDING

GCN_EMBEDDING = 512


#: The roles of what :class:`ObjectGcnMixin` builds: an observation encoder.
OBJECT_GCN_ROLES = ParameterRoles(encoder=("A", "W0", "W1", "W2", "W3", "final_mapping"))


class ObjectGcnMixin:
    def _build_object_gcn(self) -> None:
        nodes, width = self.num_categories, self.num_categories + self.glove_dim
        self.A = normalized_adjacency_parameter(self.knowledge.graph(self.graph_name()))
        self.register_buffer("all_glove", torch.tensor(self.knowledge.glove, dtype=torch.float32))
        self.W0 = nn.Linear(width, width, bias=False)
        self.W1 = nn.Linear(width, width, bias=False)
        self.W2 = nn.Linear(width, 5, bias=False)
        self.W3 = nn.Linear(10, 1, bias=False)
        self.final_mapping = nn.Linear(nodes, GCN_EMBEDDING)

    def _object_gcn(self, cm: Tensor) -> Tensor:
        x = self.per_in_view(cm[..., 0], self._in_view_layers).transpose(0, 1)  # [C, B, 5]
        x = F.relu(gcn_layer(self.A, torch.cat([x, cm.transpose(0, 1)], dim=-1), self.W3))  # [C, B, 1]
        return self.final_mapping(x.squeeze(-1).T)

    def _in_view_layers(self, in_view: Tensor) -> Tensor:
        """X3 ``[B, C, 5]``: the layers that see the observation only through the in-view vector."""
        # Every node sees all detections: X0 = [in-view vector repeated per node || node GloVe].
        shared = self.fixed_term("gcn", lambda: shared_gcn_term(self.A, self.all_glove, self.W0))
        x = F.relu(shared_row_gcn_layer(self.A, in_view, shared, self.W0), inplace=True)  # [C, B, C + 300]
        x = F.relu(gcn_layer(self.A, x, self.W1))
        return F.relu(gcn_layer(self.A, x, self.W2)).transpose(0, 1)


class MjolnirObjectModel(ObjectGcnMixin, SavnEmbeddingMixin, RecurrentNavModel):
    description = "MJOLNIR_O: context matrix + object GCN + previous policy -> LSTM(5C + 522)"
    trains_with_parent_reward = True  # MJOLNIR's --partial_reward
    default_graph = "vg"
    parameter_roles = SAVN_EMBEDDING_ROLES | OBJECT_GCN_ROLES
    # No SAVN image embedding: no dropout, and the target row enters as it is, without a distance.
    settings = RECURRENT | GRAPH | {"target_context": "", "reference_extras": ""}

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_object_gcn()
        self.embed_action = nn.Linear(NUM_ACTIONS, 10)
        # target_context: no target descriptor to put the row in, so it joins the LSTM input.
        self._finish_init(5 * self.num_categories + 10 + GCN_EMBEDDING + 4 * config.target_context)

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        cm = context_vector(obs, self.all_glove)
        action = F.relu(self.embed_action(prev_policy))
        parts = [cm.flatten(1), action, self._object_gcn(cm)]
        if self.config.target_context:
            parts.append(target_row(obs["context"], obs["target_index"]))
        return torch.cat(parts, dim=1), None


class MjolnirResnetModel(ObjectGcnMixin, SavnEmbeddingMixin, RecurrentNavModel):
    description = "MJOLNIR_R: SAVN embedding || object GCN -> LSTM(3648)"
    trains_with_parent_reward = True  # MJOLNIR's --partial_reward
    default_graph = "vg"
    parameter_roles = SAVN_EMBEDDING_ROLES | OBJECT_GCN_ROLES  # the frozen resnet18 needs no role
    settings = RECURRENT | SAVN_EMBEDDING | GRAPH

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_base_embedding()
        self._build_object_gcn()
        self._finish_init(BASE_EMBEDDING + GCN_EMBEDDING)
        if config.reference_extras:
            # MJOLNIR_R builds ResNet-18's avgpool + ImageNet fc, frozen and never used.
            self.resnet18 = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Linear(512, 1000))
            self.resnet18.requires_grad_(False)

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        cm = context_vector(obs, self.all_glove)
        return torch.cat([self._base_embedding(obs, prev_policy), self._object_gcn(cm)], dim=1), None
