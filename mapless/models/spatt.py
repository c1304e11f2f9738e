"""SpAtt (Mayo, Hazan, Tal, CVPR 2021; ``barmayo/spatial_attention`` ``EOTP``), adaptive like SAVN.

Cells s_i = Conv1d(F -> 64)(features), i over the 49 cells. Three cosine potentials per cell between
the L2-normalised (then dropped-out) ŝ_i and normalised queries from the target GloVe, the previous
hidden state and the previous policy (order target, memory, action); mixing weights
α = Conv1d(512 -> 3)(h_{t-1}) (unconstrained). Attention p = softmax_i(Σ_k α_k θ_k(i)); the attended
map ReLU(s_i)·p(i) is flattened cell by cell (64 x 49 = 3136, keeping the "where") and is the only LSTM
input.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import Knowledge
from mapless.models.base import EMBED, GRID, NUM_ACTIONS, RECURRENT_CORE_ROLES, ModelConfig, RecurrentNavModel
from mapless.models.dropout import Dropout
from mapless.models.layers import pointwise_conv, target_context_input, unit
from mapless.models.learned_loss import LEARNED_LOSS_ROLES, LearnedLossMixin
from mapless.models.roles import ParameterRoles
from mapless.models.settings import ADAPTIVE, RECURRENT


class SpattModel(LearnedLossMixin, RecurrentNavModel):
    description = "SpAtt: target/memory/action spatial attention over the 7x7 map; SAVN inner loop"
    default_inner_lr = 0.01  # barmayo/spatial_attention --inner_lr default (SAVN's is 1e-4)
    parameter_roles = (
        RECURRENT_CORE_ROLES
        | LEARNED_LOSS_ROLES
        | ParameterRoles(
            encoder=("embed_state", "embed_glove", "embed_target_context", "embed_memory", "memory_alpha"),
            policy=("embed_action",),
        )
    )
    # The target row enters the query as it is, without a distance.
    settings = RECURRENT | ADAPTIVE | {"dropout": "", "target_context": ""}
    encoder_reads_state = True  # the memory query and the mixing weights read h_{t-1}

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        hidden = self.hidden_size
        # 1x1 Conv1d layers (not Linear) keep the original checkpoint's weight shapes (out, in, 1).
        self.embed_state = nn.Conv1d(self.feature_channels, EMBED, 1)
        self.embed_glove = nn.Conv1d(self.glove_dim, EMBED, 1)
        if config.target_context:
            self.embed_target_context = nn.Conv1d(4, EMBED, 1)
        self.embed_action = nn.Conv1d(NUM_ACTIONS, EMBED, 1)
        self.embed_memory = nn.Conv1d(hidden, EMBED, 1)
        self.memory_alpha = nn.Conv1d(hidden, 3, 1)
        self.dropout = Dropout(config.dropout)
        self.build_recurrent_core(EMBED * GRID * GRID)
        self._build_learned_loss(with_key_linear=False)  # EOTP has no ll_key / ll_linear

    @staticmethod
    def _query(layer: nn.Conv1d, vector: Tensor) -> Tensor:
        return unit(pointwise_conv(layer, vector.unsqueeze(-1)).squeeze(-1))

    def _target_query(self, obs: dict[str, Tensor]) -> Tensor:
        if not self.config.target_context:
            return self._query(self.embed_glove, obs["target_embedding"])
        target = pointwise_conv(self.embed_glove, obs["target_embedding"].unsqueeze(-1)).squeeze(-1)
        return unit(target + target_context_input(obs, self.embed_target_context))

    def attention(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Returns ``(cells [B, 64, 49], attention p [B, 49])``."""
        h_prev = hidden[0]
        cells = pointwise_conv(self.embed_state, obs["features"].flatten(2))
        keys = self.dropout(unit(cells, dim=1))
        queries = torch.stack(
            [
                self._target_query(obs),
                self._query(self.embed_memory, h_prev),
                self._query(self.embed_action, prev_policy),
            ],
            dim=1,
        )  # [B, 3, 64]
        potentials = queries @ keys  # [B, 3, 49] cosine potentials
        alpha = pointwise_conv(self.memory_alpha, h_prev.unsqueeze(-1)).squeeze(-1)  # [B, 3]
        p = torch.softmax((alpha.unsqueeze(-1) * potentials).sum(dim=1), dim=-1)
        return cells, p

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        cells, p = self.attention(obs, hidden, prev_policy)
        return (F.relu(cells) * p.unsqueeze(1)).flatten(1), None
