"""SAVN's non-adaptive A3C model (``a3c``, SAVN ``BaseModel``) and ``savn`` (the same network plus the
learned interaction loss and the inner loop).

Feature map -> 1x1 conv 64 + ReLU + dropout; target GloVe -> 64 + ReLU and previous policy -> 10 + ReLU,
both tiled over the 7x7 grid; concatenation (138) -> 1x1 pointwise conv 64 + ReLU + dropout -> flatten
(3136) -> LSTMCell(3136, 512) -> actor (6) and critic (1) on h.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import Knowledge
from mapless.models.base import EMBED, GRID, NUM_ACTIONS, RECURRENT_CORE_ROLES, ModelConfig, RecurrentNavModel
from mapless.models.dropout import Dropout
from mapless.models.layers import pointwise_conv, target_context_input, tile
from mapless.models.learned_loss import LEARNED_LOSS_ROLES, LearnedLossMixin
from mapless.models.roles import ParameterRoles
from mapless.models.settings import ADAPTIVE, RECURRENT, SAVN_EMBEDDING

BASE_EMBEDDING = EMBED * GRID * GRID  # 3136


#: The roles of what :class:`SavnEmbeddingMixin` builds, the recurrent core included: the visual and
#: target embeddings are the encoders, the previous-action embedding and the fusion the policy.
SAVN_EMBEDDING_ROLES = RECURRENT_CORE_ROLES | ParameterRoles(
    encoder=("conv1", "embed_glove", "embed_target_context"),
    policy=("embed_action", "pointwise"),
    outer_only=("action_predict_linear",),
)


class SavnEmbeddingMixin:
    """SAVN's visual/target/action embedding, shared by a3c, savn, sp, gve and mjolnir_r."""

    def _build_base_embedding(self) -> None:
        self.conv1 = nn.Conv2d(self.feature_channels, EMBED, 1)
        self.embed_glove = nn.Linear(self.glove_dim, EMBED)
        if self.config.target_context:
            self.embed_target_context = nn.Linear(4 + int(self.config.context_distance), EMBED)
        self.embed_action = nn.Linear(NUM_ACTIONS, 10)
        self.pointwise = nn.Conv2d(EMBED + EMBED + 10, EMBED, 1)
        self.dropout = Dropout(self.config.dropout)

    def _base_embedding(self, obs: dict[str, Tensor], prev_policy: Tensor) -> Tensor:
        image = self.dropout(F.relu(pointwise_conv(self.conv1, obs["features"])))
        target = self.embed_glove(obs["target_embedding"])
        if self.config.target_context:
            target = target + target_context_input(
                obs, self.embed_target_context, self.config.context_distance
            )
        glove = tile(F.relu(target), GRID, GRID)
        action = tile(F.relu(self.embed_action(prev_policy)), GRID, GRID)
        x = torch.cat([image, glove, action], dim=1)
        return self.dropout(F.relu(pointwise_conv(self.pointwise, x))).flatten(1)

    def _finish_init(self, lstm_input: int) -> None:
        """LSTM and heads, SAVN's init, then the reference's dead ``action_predict_linear``."""
        self.build_recurrent_core(lstm_input)
        if hasattr(self, "conv1"):
            with torch.no_grad():
                self.conv1.weight.mul_(math.sqrt(2.0))  # SAVN scales conv1 by the ReLU gain
        if self.config.reference_extras:
            # Defined by every reference model (2 x LSTM input -> 6) and never called.
            self.action_predict_linear = nn.Linear(2 * lstm_input, NUM_ACTIONS)


class A3CModel(SavnEmbeddingMixin, RecurrentNavModel):
    description = "SAVN's non-adaptive A3C (ResNet map + GloVe + previous policy -> LSTM)"
    parameter_roles = SAVN_EMBEDDING_ROLES
    settings = RECURRENT | SAVN_EMBEDDING

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_base_embedding()
        self._finish_init(BASE_EMBEDDING)

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        return self._base_embedding(obs, prev_policy), None


class SavnModel(LearnedLossMixin, A3CModel):
    description = "SAVN: a3c + learned interaction loss, inner SGD steps at train and test time"
    default_inner_lr = 1e-4  # allenai/savn --inner_lr default
    parameter_roles = SAVN_EMBEDDING_ROLES | LEARNED_LOSS_ROLES
    settings = RECURRENT | SAVN_EMBEDDING | ADAPTIVE

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        self._build_learned_loss(with_key_linear=True)
